"""The offline commands through click: exit codes, one-line messages, outputs, provenance."""

import contextlib
import json
import logging
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import gsc, rewrite_log
from mcap.writer import CompressionType

from gscompress.gaussians import GaussianMap, random_map
from gscompress.io.mcap_log import (
    LogMetadata,
    LogReader,
    LogWriter,
    gaussians_to_pointcloud,
    read_map,
)
from gscompress.io.ply import read_ply, write_ply
from gscompress.pipeline import log_info
from gscompress_cli.main import cli
from gscompress_schemas import PROFILE


@pytest.fixture()
def log_path(tmp_path):
    """A small log: calibration, three poses, two snapshots (the last with 1000 Gaussians)."""
    from gscompress.camera import Intrinsics

    path = tmp_path / "run.mcap"
    with LogWriter(path, LogMetadata(command="test", sequence="synthetic")) as log:
        log.write_calibration(Intrinsics(50, 50, 16, 12, 32, 24), 0)
        for i in range(3):
            log.write_pose(np.eye(4), i)
        log.write_gaussians(random_map(400, seed=1), 1)
        log.write_gaussians(random_map(1000, seed=2), 2)
    return path


def snapshot_of(path):
    return {p.name for p in path.parent.iterdir()}


def test_prune_keeps_top_fraction_and_passes_the_rest_through(log_path, tmp_path):
    out = tmp_path / "p.mcap"
    r = gsc("prune", log_path, "--keep", "0.3", "--no-fold", "-o", out)
    assert r.exit_code == 0, r.output
    assert "kept 300 of 1000 Gaussians (by pwas, fp32)" in r.output
    full, pruned = read_map(log_path), read_map(out)
    assert len(pruned) == 300
    assert pruned.importance.min() >= np.setdiff1d(full.importance, pruned.importance).max()
    with LogReader(log_path) as a, LogReader(out) as b:
        assert [(c.topic, c.messages) for c in a.channels] == [
            (c.topic, c.messages) for c in b.channels
        ]
        assert a.read_map(0).equals(b.read_map(0))  # earlier snapshots unchanged
        raw_a = [
            (ch.topic, m.log_time, m.data) for _, ch, m in a.iter_messages(["/camera/pose", "/tf"])
        ]
        raw_b = [
            (ch.topic, m.log_time, m.data) for _, ch, m in b.iter_messages(["/camera/pose", "/tf"])
        ]
        assert raw_a == raw_b
        step = b.metadata.provenance[-1]
        assert step["operation"] == {
            "name": "prune",
            "keep": 0.3,
            "by": "pwas",
            "seed": 0,
            "fold": False,
        }
        assert step["parent"] == "run.mcap" and b.metadata.sequence == "synthetic"
        assert b.metadata.results == {"kept": 300, "total": 1000, "codec": "fp32", "fold": False}


def test_prune_map_only_writes_the_same_map_alone(log_path, tmp_path):
    full, alone = tmp_path / "p.mcap", tmp_path / "m.mcap"
    assert gsc("prune", log_path, "--keep", "0.3", "-o", full).exit_code == 0
    r = gsc("prune", log_path, "--keep", "0.3", "--map-only", "-o", alone)
    assert r.exit_code == 0, r.output
    with LogReader(full) as a, LogReader(alone) as b:
        assert b.snapshot_count == 1
        assert {c.topic: c.messages for c in b.channels} == {
            "/camera/calibration": 1,
            "/gaussians": 1,
        }
        (_, _, last_a), (_, _, only_b) = (
            list(a.iter_messages(["/gaussians"]))[-1],
            next(iter(b.iter_messages(["/gaussians"]))),
        )
        assert last_a.data == only_b.data and last_a.log_time == only_b.log_time  # bit-exact
        step = b.metadata.provenance[-1]
        assert step["operation"]["map_only"] is True and step["parent"] == "run.mcap"
        assert b.metadata.sequence == "synthetic" and b.metadata.results["kept"] == 300
    assert alone.stat().st_size < full.stat().st_size


def test_prune_by_opacity_and_percent_syntax(log_path, tmp_path):
    out = tmp_path / "p.mcap"
    r = gsc("prune", log_path, "--keep", "10%", "--by", "opacity", "--no-fold", "-o", out, "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["kept"] == 100
    full, pruned = read_map(log_path), read_map(out)
    assert (
        pruned.opacity_logits.min()
        >= np.setdiff1d(full.opacity_logits, pruned.opacity_logits).max()
    )


def test_share_writes_mcap_and_ply_with_its_record(log_path, tmp_path):
    out, ply = tmp_path / "s.mcap", tmp_path / "s.ply"
    r = gsc("share", "--budget", "0.2", log_path, out, "--ply", ply, "--strategy", "pwas")
    assert r.exit_code == 0, r.output
    shared = read_map(out)
    assert len(shared) == 200
    assert read_ply(ply).equals(shared)
    with LogReader(out) as s:
        assert s.metadata.results == {
            "source": "run.mcap",
            "strategy": "pwas",
            "budget": 0.2,
            "codec": "compact",  # the default
            "sums": True,
            "ids": False,  # the default
            "fold": True,  # the default
            "bytes": log_info(out)["map"]["bytes"],
            "selected": 200,
            "total": 1000,
        }
        assert [c.topic for c in s.channels] == ["/gaussians"]
    assert log_info(out)["map"]["bytes_per_gaussian"] < 30  # 76 as fp32
    r = gsc("share", log_path, "-o", tmp_path / "o.mcap")  # -o as the other commands take it
    assert r.exit_code == 0 and read_map(tmp_path / "o.mcap").equals(shared)
    for paths, message in (
        ([], "missing the share's path: give DST or -o"),
        ([tmp_path / "x.mcap", "-o", tmp_path / "y.mcap"], "as DST or with -o, not both"),
    ):
        r = gsc("share", log_path, *paths)
        assert r.exit_code == 2 and message in r.output
    same = tmp_path / "q.mcap"
    r = gsc("share", log_path, same, "--ply", same)
    assert r.exit_code == 2 and "--ply must differ" in r.output and not same.exists()


def test_share_whose_ply_cannot_be_written_leaves_no_mcap(log_path, tmp_path, monkeypatch):
    """The share is written whole or not at all: a PLY refused by the file system (as on a
    read-only mount that passes the permission check) takes the fresh MCAP with it."""
    import errno

    from gscompress.pipeline import share

    def refuse(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", str(tmp_path / "s.ply"))

    monkeypatch.setattr(share, "write_ply", refuse)
    r = gsc("share", log_path, tmp_path / "s.mcap", "--ply", tmp_path / "s.ply")
    assert r.exit_code == 1 and r.output == f"Error: {tmp_path / 's.ply'}: Read-only file system\n"
    assert list(tmp_path.iterdir()) == [log_path]


def test_export_ply_last_and_chosen_snapshot(log_path, tmp_path):
    r = gsc("export-ply", log_path, "-o", tmp_path / "a.ply")
    assert r.exit_code == 0, r.output
    assert read_ply(tmp_path / "a.ply").equals(read_map(log_path))
    r = gsc("export-ply", log_path, "-o", tmp_path / "b.ply", "--snapshot", "0")
    assert r.exit_code == 0 and len(read_ply(tmp_path / "b.ply")) == 400
    r = gsc("export-ply", log_path, "-o", tmp_path / "c.ply", "--snapshot", "-1", "--json")
    with LogReader(log_path) as log:  # the snapshot it wrote, counted from 0
        assert json.loads(r.output)["snapshot"] == log.snapshot_count - 1 > 0


def test_import_ply_then_info(tmp_path):
    g = random_map(50, scored=False, sh_degree=3, isotropic=False)
    write_ply(g, tmp_path / "in.ply", importance=False)
    r = gsc("import-ply", tmp_path / "in.ply", "-o", tmp_path / "m.mcap")
    assert r.exit_code == 0, r.output
    back = read_map(tmp_path / "m.mcap")
    assert back.means.tobytes() == g.means.tobytes() and back.sh_degree == 3
    r = gsc("info", tmp_path / "m.mcap")
    assert r.exit_code == 0 and "importance none" in r.output and "import-ply" in r.output
    r = gsc("info", tmp_path / "in.ply")  # a PLY where a log belongs: the error says what to do
    assert r.exit_code == 1 and "(it is a PLY file; `gsc import-ply` makes a log of it)" in r.output
    r = gsc("prune", tmp_path / "m.mcap", "--keep", "0.5", "-o", tmp_path / "p.mcap")
    assert r.exit_code == 1 and "gsc score" in r.output
    assert not (tmp_path / "p.mcap").exists()
    # the other score it suggests is an option of both commands that can meet the error
    assert "(--by opacity)" in r.output
    for command, ratio in (("prune", "--keep"), ("share", "--budget")):
        out = tmp_path / f"{command}.mcap"
        r = gsc(command, tmp_path / "m.mcap", ratio, "0.5", "--by", "opacity", "-o", out)
        assert r.exit_code == 0 and out.exists(), r.output


def test_info_json_describes_the_log(log_path, tmp_path):
    gsc("share", log_path, tmp_path / "s.mcap", "--codec", "fp32")
    r = gsc("info", tmp_path / "s.mcap", "--json")
    assert r.exit_code == 0, r.output
    info = json.loads(r.output)
    assert info["map"]["gaussians"] == 200 and info["map"]["has_importance"]
    q = info["map"]["importance_quantiles"]
    assert q["q00"] <= q["q50"] <= q["q100"]
    assert sum(info["map"]["importance_histogram"]["counts"]) == 200
    assert info["map"]["codec"] == "fp32" and info["snapshots"][0]["codec"] == "fp32"
    assert 200 * 76 < info["map"]["bytes"] < 200 * 76 + 1000  # plus the PointCloud header
    assert info["map"]["bytes_per_gaussian"] == info["map"]["bytes"] / 200
    assert info["map"]["bytes"] == info["results"]["bytes"]
    assert info["provenance"][0]["operation"]["name"] == "share"
    assert info["channels"] == [
        {
            "topic": "/gaussians",
            "schema": "foxglove.PointCloud",
            "encoding": "protobuf",
            "messages": 1,
        }
    ]


# ---------------------------------------------------------------- bad input


def _truncated(src, dst):
    dst.write_bytes(src.read_bytes()[: src.stat().st_size // 2])


def _cut_short(src, dst):
    dst.write_bytes(src.read_bytes()[:10])  # the magic and two bytes: no record to seek through


def _corrupt_chunk(src, dst):
    """16 bytes flipped in the first zstd block of the log's largest chunk: zstd finds the
    damage before the chunk's CRC is checked."""
    with LogReader(src) as log:
        chunk = max(log._summary.chunk_indexes, key=lambda c: c.compressed_size)
    data = bytearray(src.read_bytes())
    at = chunk.chunk_start_offset + chunk.chunk_length - chunk.compressed_size + 12
    data[at : at + 16] = bytes(b ^ 0x5A for b in data[at : at + 16])
    dst.write_bytes(bytes(data))


def _corrupt_lz4_chunk(src, dst):
    """The log re-chunked with lz4 (as other MCAP tools may write it), then the frame
    descriptor of its largest chunk's lz4 data flipped: lz4 itself rejects the chunk."""
    rewrite_log(src, dst, PROFILE, compression=CompressionType.LZ4)
    with LogReader(dst) as log:
        chunk = max(log._summary.chunk_indexes, key=lambda c: c.compressed_size)
    data = bytearray(dst.read_bytes())
    at = chunk.chunk_start_offset + chunk.chunk_length - chunk.compressed_size + 4
    data[at] ^= 0xFF
    dst.write_bytes(bytes(data))


def _no_gaussians(src, dst):
    with LogWriter(dst, LogMetadata()) as log:
        log.write_pose(np.eye(4), 0)


def _bad_stride(src, dst):
    cloud = gaussians_to_pointcloud(random_map(10))
    cloud.data = cloud.data[:-5]
    with LogWriter(dst, LogMetadata()) as log:
        log.write_protobuf("/gaussians", cloud, 0)


def _non_finite(src, dst):
    g = random_map(10)
    g.means[0, 0] = np.nan
    with LogWriter(dst, LogMetadata()) as log:
        log.write_gaussians(g, 0)


def _not_mcap(src, dst):
    dst.write_text("this is not an mcap file\n")


def _empty(src, dst):
    dst.write_bytes(b"")


def _a_ply(src, dst):
    write_ply(random_map(5), dst.with_suffix(".ply"))
    dst.write_bytes(dst.with_suffix(".ply").read_bytes())


def _newer_profile(src, dst):
    with LogWriter(dst, LogMetadata(profile_version="99.0")) as log:
        log.write_gaussians(random_map(10), 0)


@pytest.mark.parametrize(
    "make_input, message",
    [
        (_not_mcap, "not a readable MCAP log (it does not begin as an MCAP file does)"),
        (_empty, "not a readable MCAP log (the file is empty)"),
        (_a_ply, "(it is a PLY file; `gsc import-ply` makes a log of it)"),
        (_truncated, "MCAP file is truncated"),
        (_cut_short, "MCAP file is truncated"),
        (_corrupt_chunk, "zstd data is corrupt"),
        (_corrupt_lz4_chunk, "lz4 data is corrupt (LZ4"),
        (_no_gaussians, "no /gaussians channel"),
        (_bad_stride, "not a multiple of point_stride"),
        (_non_finite, "non-finite"),
        (_newer_profile, "newer than this gscompress"),
    ],
)
@pytest.mark.parametrize("command", ["prune", "share", "export-ply", "info"])
def test_bad_logs_give_one_line_error_and_no_output(
    log_path, tmp_path, make_input, message, command
):
    bad = tmp_path / "bad.mcap"
    make_input(log_path, bad)
    before = snapshot_of(bad)
    args = {
        "prune": ("prune", bad, "--keep", "0.3", "-o", tmp_path / "out.mcap"),
        "share": ("share", bad, tmp_path / "out.mcap", "--ply", tmp_path / "out.ply"),
        "export-ply": ("export-ply", bad, "-o", tmp_path / "out.ply"),
        "info": ("info", bad),
    }[command]
    r = gsc(*args)
    if command == "info" and make_input is _no_gaussians:
        assert r.exit_code == 0 and "no /gaussians channel" in r.output
        return
    assert r.exit_code == 1, r.output
    assert message in r.output
    assert r.output.count("\n") == 1 and r.output.startswith("Error: ")
    assert "Traceback" not in r.output
    assert snapshot_of(bad) == before  # no output, no temporary file left behind


@pytest.mark.parametrize("value", ["0", "-0.1", "1.5", "abc", "nan"])
def test_ratio_outside_range(log_path, tmp_path, value):
    r = gsc("prune", log_path, "--keep", value, "-o", tmp_path / "o.mcap")
    assert r.exit_code == 2 and "--keep" in r.output
    r = gsc("share", log_path, tmp_path / "o.mcap", "--budget", value)
    assert r.exit_code == 2 and "--budget" in r.output
    assert not (tmp_path / "o.mcap").exists()


MISSING_INPUTS = [
    ("info", "{x}"),
    ("prune", "{x} -o {o}.mcap"),
    ("share", "{x} -o {o}.mcap"),
    ("export-ply", "{x} -o {o}.ply"),
    ("import-ply", "{x} -o {o}.mcap"),
    ("eval", "{x} --seq {d}"),
    ("eval", "{log} --seq {x}"),
    ("score", "{x} --seq {d} -o {o}.mcap"),
    ("score", "{log} --seq {x} -o {o}.mcap"),
    ("merge", "{x} {log} --iters 0 -o {o}.mcap"),
    ("merge", "{log} {x} --iters 0 -o {o}.mcap"),
    ("merge", "{log} {log} --seq {x} -o {o}.mcap"),
    ("merge", "{log} {log} --share-transform {x} --iters 0 -o {o}.mcap"),
    ("slam", "{x} -o {o}.mcap"),
    ("slam", "{d} --inject {x} -o {o}.mcap"),
    ("experiment", "{x} -o {o}"),
]


@pytest.mark.parametrize(("command", "args"), MISSING_INPUTS)
def test_a_missing_input_is_a_usage_error_naming_it(log_path, tmp_path, command, args):
    """Every command: exit 2 (as for any bad argument), the path named, nothing written."""
    missing, out = tmp_path / "nosuch", tmp_path / "out"
    values = {"x": missing, "o": out, "log": log_path, "d": tmp_path}
    r = gsc(command, *args.format(**values).split())
    assert r.exit_code == 2, r.output
    assert "nosuch" in r.output and "does not exist" in r.output, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]


@pytest.mark.parametrize(
    ("args", "where"),
    [
        (["prune", "{log}", "--keep", "1.5", "-o", "{o}"], "gsc prune"),
        (["share", "{log}"], "gsc share"),
        (["slam", "{d}", "--frames", "bogus", "-o", "{o}"], "gsc slam"),
        (["nosuch-command"], "gsc"),
        (["--threads", "0", "info", "{log}"], "gsc"),
    ],
)
def test_a_usage_error_is_one_line_pointing_to_help(log_path, tmp_path, args, where):
    values = {"log": log_path, "o": tmp_path / "o.mcap", "d": tmp_path}
    r = CliRunner().invoke(cli, [a.format(**values) for a in args], prog_name="gsc")
    assert r.exit_code == 2, r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.output
    assert lines[0].endswith(f"(see '{where} --help')"), r.output


def test_output_equal_to_input_and_existing_output(log_path, tmp_path):
    original = log_path.read_bytes()
    r = gsc("prune", log_path, "--keep", "0.3", "-o", log_path, "--force")
    assert r.exit_code == 1 and "also an input" in r.output
    r = gsc("export-ply", log_path, "-o", log_path, "--force")
    assert r.exit_code == 1 and "also an input" in r.output
    link = tmp_path / "link.mcap"
    link.symlink_to(log_path)
    r = gsc("share", log_path, link, "--force")
    assert r.exit_code == 1 and "also an input" in r.output
    assert log_path.read_bytes() == original
    existing = tmp_path / "exists.mcap"
    existing.write_bytes(b"precious")
    r = gsc("prune", log_path, "--keep", "0.3", "-o", existing)
    assert r.exit_code == 1 and "--force" in r.output and existing.read_bytes() == b"precious"
    r = gsc("prune", log_path, "--keep", "0.3", "-o", existing, "--force")
    assert r.exit_code == 0 and len(read_map(existing)) == 300


def test_an_output_named_for_the_other_format_is_refused(log_path, tmp_path):
    r = gsc("prune", log_path, "--keep", "0.3", "-o", tmp_path / "p.ply")
    assert r.exit_code == 1 and "name it p.mcap (gsc export-ply writes PLY)" in r.output
    r = gsc("export-ply", log_path, "-o", tmp_path / "m.mcap")
    assert r.exit_code == 1 and "writes a PLY file, not an MCAP log" in r.output
    r = gsc("share", log_path, tmp_path / "s.mcap", "--ply", tmp_path / "s.mcap.mcap")
    assert r.exit_code == 1 and "name it s.mcap.ply" in r.output
    r = gsc("export-traj", log_path, "-o", tmp_path / "t.mcap")
    assert r.exit_code == 1 and "writes a text file, not an MCAP log; name it t.txt" in r.output
    r = gsc("prune", log_path, "--keep", "0.3", "-o", tmp_path / "p.txt")
    assert r.exit_code == 1 and "writes an MCAP log, not a text file" in r.output
    written = {p.name for p in tmp_path.iterdir()} - {log_path.name}
    assert written == set()  # nothing written, the MCAP share included


def test_ply_missing_properties(tmp_path):
    from plyfile import PlyData, PlyElement

    data = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "pts.ply"))
    r = gsc("import-ply", tmp_path / "pts.ply", "-o", tmp_path / "m.mcap")
    assert r.exit_code == 1 and "missing vertex properties" in r.output
    assert not (tmp_path / "m.mcap").exists()


def test_offline_commands_do_not_import_torch(log_path, tmp_path):
    runs = [
        ["prune", str(log_path), "--keep", "0.3", "-o", str(tmp_path / "p.mcap")],
        ["prune", str(log_path), "--keep", "0.3", "--map-only", "-o", str(tmp_path / "m.mcap")],
        ["share", str(log_path), str(tmp_path / "s.mcap")],  # compact: encoded
        ["info", str(tmp_path / "s.mcap")],  # and decoded
        [
            "prune",
            str(log_path),
            "--keep",
            "0.3",
            "--codec",
            "compact",
            "-o",
            str(tmp_path / "c.mcap"),
        ],
        ["share", str(log_path), str(tmp_path / "b.mcap"), "--budget", "20%bytes", "--no-sums"],
        ["export-ply", str(log_path), "-o", str(tmp_path / "e.ply")],
        ["export-traj", str(log_path), "-o", str(tmp_path / "t.txt")],
        ["info", str(log_path)],
    ]
    code = (
        "import json, sys\n"
        "from gscompress_cli.main import cli\n"
        "for args in json.loads(sys.argv[1]):\n"
        "    try:\n"
        "        cli(args)\n"
        "    except SystemExit as e:\n"
        "        assert e.code == 0, e\n"
        "print('torch' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, json.dumps(runs)], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip().splitlines()[-1] == "False"
    assert (tmp_path / "e.ply").exists() and (tmp_path / "t.txt").exists()


def test_default_verbosity_prints_results_and_warnings_not_module_notes(log_path, tmp_path):
    """A command's own notes (SPZ keeps no scores) are for -v; a warning says it is one, without
    the logger's name; -v names the level and logger of every line."""

    def gsc(*args: object) -> subprocess.CompletedProcess:
        cmd = [sys.executable, "-m", "gscompress_cli", *map(str, args)]
        return subprocess.run(cmd, capture_output=True, text=True, check=True)

    out = gsc("export-ply", log_path, "-o", tmp_path / "a.spz")
    assert out.stdout.startswith("wrote ") and out.stderr == ""
    out = gsc("-v", "export-ply", log_path, "-o", tmp_path / "b.spz")
    assert "DEBUG gscompress.io.map_files: SPZ stores no importance scores" in out.stderr
    from gscompress_cli.main import ConsoleFormatter

    record = logging.LogRecord("gscompress.x", logging.WARNING, "", 0, "look out", None, None)
    assert ConsoleFormatter(named=False).format(record) == "warning: look out"
    record.levelno, record.levelname = logging.INFO, "INFO"
    assert ConsoleFormatter(named=False).format(record) == "look out"
    assert ConsoleFormatter(named=True).format(record) == "INFO gscompress.x: look out"


def test_help_teaches():
    r = gsc("--help")
    assert r.exit_code == 0
    for name in ("prune", "share", "export-ply", "info", "import-ply"):
        assert name in r.output
    r = gsc("prune", "--help")
    assert "Example" in r.output and "--keep" in r.output


# ---------------------------------------------------------------- byte budgets


@pytest.mark.parametrize(
    "value, message",
    [
        ("2", "add a unit"),
        ("2XB", "unknown unit"),
        ("0B", "at least 1 B"),
        ("MB", "neither a fraction"),
    ],
)
def test_bad_budget_strings_are_usage_errors(log_path, tmp_path, value, message):
    r = gsc("share", log_path, tmp_path / "o.mcap", "--budget", value)
    assert r.exit_code == 2 and "--budget" in r.output and message in r.output
    assert "Traceback" not in r.output and not (tmp_path / "o.mcap").exists()


def test_budget_below_one_gaussian_is_a_one_line_error(log_path, tmp_path):
    r = gsc("share", log_path, tmp_path / "o.mcap", "--budget", "400B")
    assert r.exit_code == 1 and r.output.startswith("Error: ") and r.output.count("\n") == 1
    assert "cannot hold one Gaussian" in r.output and not (tmp_path / "o.mcap").exists()


def test_share_byte_budget_fp16_then_info(log_path, tmp_path):
    out, ply = tmp_path / "s.mcap", tmp_path / "s.ply"
    r = gsc("share", "--budget", "20kB", "--codec", "fp16", log_path, out, "--ply", ply)
    assert r.exit_code == 0, r.output
    assert "fp16" in r.output
    r = gsc("share", "--budget", "20kB", "--codec", "fp16", log_path, out, "--json", "--force")
    result = json.loads(r.output)
    assert result["budget"] == "20kB" and result["budget_bytes"] == 20_000
    assert result["codec"] == "fp16" and out.stat().st_size == result["file_bytes"] <= 20_000
    assert read_ply(ply).equals(read_map(out))
    r = gsc("info", out)
    assert r.exit_code == 0, r.output
    assert f"{result['selected']} Gaussians, isotropic, SH degree 0, codec fp16" in r.output
    per = result["bytes"] / result["selected"]
    assert f"bytes     {result['bytes']} B" in r.output and f"{per:.2f} B per Gaussian" in r.output
    r = gsc("share", "--help")
    assert "2MB" in r.output and "1.5MiB" in r.output and "--codec" in r.output
    # a share is compact unless asked otherwise; --precision is an old name of --codec
    r = gsc("share", "--budget", "0.5", out, tmp_path / "again.mcap", "--json")
    assert json.loads(r.output)["codec"] == "compact", r.output
    r = gsc(
        "share", "--budget", "0.5", "--precision", "fp32", out, tmp_path / "wide.mcap", "--json"
    )
    assert json.loads(r.output)["codec"] == "fp32", r.output
    r = gsc("share", "--precision", "fp32", "--codec", "fp16", out, tmp_path / "x.mcap")
    assert r.exit_code == 2 and "--precision is an old name of --codec" in r.output
    r = gsc("share", "--budget", "0.5", "--by", "opacity", log_path, tmp_path / "o.mcap", "--json")
    assert json.loads(r.output)["strategy"] == "opacity", r.output


def test_a_share_without_ids_holds_more_of_the_map_in_a_byte_budget(log_path, tmp_path):
    """Without ids (the default) a share sends the same Gaussians as --ids, numbered 0..N-1 by
    the reader, in fewer bytes; so a byte budget holds more of them, and the budget still
    holds. fp32 keeps its ids."""

    def share(*args: object) -> tuple[dict, GaussianMap]:
        out = tmp_path / f"s{len(list(tmp_path.iterdir()))}.mcap"
        r = gsc("share", log_path, out, "--json", "--no-fold", *args)
        assert r.exit_code == 0, r.output
        return {**json.loads(r.output), "dst": out.name}, read_map(out)

    (with_ids, a), (without, b) = share("--budget", "0.5", "--ids"), share("--budget", "0.5")
    assert without["selected"] == with_ids["selected"] == len(b)
    assert without["file_bytes"] < with_ids["file_bytes"] - len(b)  # over a byte a Gaussian
    assert with_ids["ids"] is True and without["ids"] is False
    assert np.array_equal(b.ids, np.arange(len(b))) and not np.array_equal(a.ids, b.ids)
    assert np.array_equal(a.means, b.means) and np.array_equal(a.importance, b.importance)
    budget = with_ids["file_bytes"]
    (fits, _), (more, _) = share("--budget", f"{budget}B", "--ids"), share("--budget", f"{budget}B")
    assert more["selected"] > fits["selected"] and more["file_bytes"] <= budget
    wide, shared = share("--budget", "0.5", "--codec", "fp32")
    assert wide["ids"] is True and np.array_equal(np.sort(shared.ids), np.sort(a.ids))
    with LogReader(tmp_path / without["dst"]) as log:
        assert log.metadata.provenance[-1]["operation"]["ids"] is False


def test_info_histogram_is_log_scaled_so_a_long_tail_does_not_hide_the_shape(tmp_path):
    """PWAS scores span decades. A linear histogram of scores that are log-uniform over 0.01-100
    with one at 0 puts three quarters in its first bin; the log-scaled one spreads them evenly
    and counts the zero apart. The text line shows the log one with its range."""
    g = random_map(1001)
    g.importance_sum[:] = np.concatenate([[0.0], np.logspace(-2, 2, 1000)])
    g.importance_weight[:] = 1.0
    with LogWriter(tmp_path / "m.mcap", LogMetadata()) as log:
        log.write_gaussians(g, 0)
    info = json.loads(gsc("info", tmp_path / "m.mcap", "--json").output)["map"]
    linear, log = info["importance_histogram"], info["importance_histogram_log"]
    assert linear["counts"][0] > 750  # the three decades below 10 of the four
    assert log["zeros"] == 1 and sum(log["counts"]) == 1000
    assert max(log["counts"]) - min(log["counts"]) <= 2  # 100 per bin, give or take an edge
    assert np.allclose(np.diff(np.log10(log["edges"])), 0.4)
    text = gsc("info", tmp_path / "m.mcap").output
    line = next(x for x in text.splitlines() if x.startswith("histogram"))
    assert line == "histogram |██████████| log scale, 0.01 to 100; 1 at 0", line
    g.importance_sum[:] = 0.0  # scored, every score 0: no range to make up
    with LogWriter(tmp_path / "z.mcap", LogMetadata()) as log:
        log.write_gaussians(g, 0)
    assert "histogram every score is 0" in gsc("info", tmp_path / "z.mcap").output


def test_info_text_rounds_floats_also_within_lists() -> None:
    from gscompress_cli.info import _value

    assert _value(0.46049840737660336) == "0.460498"
    assert _value([[0.9800665858, -0.198669291533], [1, "a"]]) == "[[0.980067, -0.198669], [1, a]]"
    assert _value(7050) == "7050" and _value(None) == "None"


def test_a_group_option_after_the_command_says_where_it_goes(tmp_path):
    r = CliRunner().invoke(
        cli, ["info", str(tmp_path / "x.mcap"), "--threads", "1"], prog_name="gsc"
    )
    assert r.exit_code == 2
    assert "--threads is an option of gsc itself" in r.output
    assert "gsc --threads N info ..." in r.output
    r = CliRunner().invoke(cli, ["info", str(tmp_path / "x.mcap"), "--thread", "1"])
    assert r.exit_code == 2 and "option of" not in r.output


def test_the_command_list_gives_every_command_a_whole_summary():
    r = gsc("--help")
    listed = r.output.split("Commands:")[1].strip().splitlines()
    from gscompress_cli.main import COMMANDS

    assert len(listed) == len(COMMANDS) and not any(line.endswith("...") for line in listed)


def test_log_lines_go_above_a_shown_bar_and_handlers_come_back(monkeypatch):
    import io
    import logging

    from tqdm import tqdm

    from gscompress_cli import progress

    stream = io.StringIO()
    console = logging.StreamHandler(stream)
    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", [console])
    monkeypatch.setattr(logging.getLogger("gscompress"), "level", logging.INFO)
    cleared_for: list[object] = []  # the files a shown bar was cleared from, for a line

    @contextlib.contextmanager
    def around(cls, file=None, nolock=False):  # type: ignore[no-untyped-def]
        cleared_for.append(file)
        yield

    monkeypatch.setattr(tqdm, "external_write_mode", classmethod(around))
    say = logging.getLogger("gscompress.t").warning
    with pytest.raises(RuntimeError), progress.progress_bar("t", "x", total=3) as bar:
        say("early")  # the bar is still in its delay: nothing to write around
        bar.delay = 0  # shown from now on
        say("late")
        raise RuntimeError
    assert stream.getvalue() == "early\nlate\n" and cleared_for == [stream]
    assert root.handlers == [console]  # put back, after an exception too


def test_format_shares_send_the_whole_map_in_each_format(log_path, tmp_path):
    from scipy.spatial import cKDTree

    from gscompress.errors import InputError
    from gscompress.io.sog import splat_transform
    from gscompress.pipeline.share.formats import format_share

    full = read_map(log_path)
    sizes = {}
    for fmt in ("fp32", "spz", *(("sog",) if splat_transform() else ())):
        out = tmp_path / f"{fmt}.mcap"
        got = format_share(log_path, out, fmt)
        back = read_map(out)
        assert got["format"] == fmt and got["selected"] == len(back) == len(full)
        dist, idx = cKDTree(back.means).query(full.means)
        assert len(np.unique(idx)) == len(full) and dist.max() < 2e-3  # within the format's steps
        assert fmt != "fp32" or dist.max() == 0
        with LogReader(out) as log:  # in the sender's world frame, without its config
            assert log.metadata.sequence == "synthetic" and log.metadata.config == {}
            name = log.metadata.provenance[-1]["operation"]["name"]
        assert name == ("share" if fmt == "fp32" else "format-share")
        sizes[fmt] = got["bytes"]
    assert sizes["spz"] < sizes["fp32"] / 3
    with pytest.raises(InputError, match="unknown format 'ply'"):
        format_share(log_path, tmp_path / "x.mcap", "ply")
    assert not (tmp_path / "x.mcap").exists()


def test_a_bar_is_drawn_while_its_count_stands_still_and_a_closed_console_stops_no_one(
    monkeypatch,
):
    """The bar of a long step is drawn again without an update (its clock moves); a console
    that cannot be written (a closed pipe) ends that drawing, and leaves no lock held that the
    command's own updates would wait for (tqdm's `refresh` keeps its locks when its drawing
    raises)."""
    import io
    import threading

    import gscompress_cli.progress as progress

    monkeypatch.setattr(progress, "HEARTBEAT_SECONDS", 0.01)  # (not a terminal)
    drawn, refused = threading.Event(), threading.Event()

    class Console(io.StringIO):
        broken = False

        def write(self, text: str) -> int:
            if self.broken:
                refused.set()
                raise BrokenPipeError(32, "Broken pipe")
            drawn.set()
            return super().write(text)

    console = Console()
    monkeypatch.setattr(sys, "stderr", console)
    monkeypatch.setattr(logging.getLogger("gscompress"), "level", logging.INFO)
    with progress.progress_bar("step", "it", total=3) as bar:
        assert drawn.wait(30)  # drawn after its delay, though nothing moved it
        console.broken = True
        assert refused.wait(30)  # the drawing thread met the closed console
        free: list[bool] = []

        def probe() -> None:  # (on a thread of its own: the locks are reentrant)
            for lock in bar.get_lock().locks:
                free.append(lock.acquire(timeout=10))
                if free[-1]:
                    lock.release()

        worker = threading.Thread(target=probe, daemon=True)
        worker.start()
        worker.join(60)
        bar.disable = True  # (the console is gone: no closing line, nor its lock)
        assert free == [True] * len(bar.get_lock().locks), "a lock stays held"
