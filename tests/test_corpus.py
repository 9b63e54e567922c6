"""Files an earlier gsc wrote (tests/corpus/, README there) read by every command that takes them.

Each corpus file goes through each command that takes such a file, through click; what the
earlier gsc reported of it (tests/corpus/expected.json) is what today's must report: the same
`gsc info --json` fields, trajectories, Gaussian and pose counts, evaluation and alignment. A
change that strands these files, or reads them differently, fails here; one that means to change
what a command reports of them says so by editing expected.json in the same commit.
"""

from __future__ import annotations

import hashlib
import json
import math
import shlex
import shutil
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import gsc
from PIL import Image

from gscompress.gaussians import GaussianMap
from gscompress.io.codec import CODECS
from gscompress.io.mcap_log import TOPIC_POSE, LogReader, read_map
from gscompress.io.ply import read_ply
from gscompress.pipeline.share import cut
from gscompress.selection import keep_count

CORPUS = Path(__file__).resolve().parent / "corpus"
EXPECTED: dict[str, Any] = json.loads((CORPUS / "expected.json").read_text(encoding="utf-8"))
FILES = sorted(EXPECTED["files"])
LOGS = [name for name in FILES if EXPECTED["files"][name]["trajectory"] is not None]
"""The corpus files that carry estimated poses (SLAM logs and what was made from them whole)."""
SHARES = [name for name in FILES if name.startswith("share_")]
WORKING_SIZE = "32x24"
"""The size the corpus's SLAM runs worked at (their sequence is 64x48)."""


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sequence the corpus was made from, written again; its folder keeps the name `seq`,
    which the logs' world frame (`ground-truth:seq`) names."""
    path = tmp_path_factory.mktemp("corpus") / "seq"
    r = gsc("synth", path, *EXPECTED["sequence"]["synth"])
    assert r.exit_code == 0, r.output
    return path


@pytest.fixture(scope="module")
def identity(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A transform file holding the identity (`tx ty tz qx qy qz qw`)."""
    path = tmp_path_factory.mktemp("transform") / "identity.txt"
    path.write_text("0 0 0 0 0 0 1\n", encoding="utf-8")
    return path


def info(name: str) -> dict[str, Any]:
    """What the earlier gsc's `gsc info --json` said of the corpus file `name`."""
    recorded: dict[str, Any] = EXPECTED["files"][name]["info"]
    return recorded


def gaussians(name: str) -> int:
    """The Gaussian count of the map of `name`, as the earlier gsc read it."""
    return int(info(name)["map"]["gaussians"])


def pose_count(name: str) -> int:
    """How many estimated poses `name` holds, as the earlier gsc read it."""
    return sum(c["messages"] for c in info(name)["channels"] if c["topic"] == TOPIC_POSE)


def rows(trajectory: str) -> list[str]:
    """The pose lines of a TUM trajectory's text (not its comments)."""
    return [line for line in trajectory.splitlines() if not line.startswith("#")]


def views_of(name: str) -> tuple[object, ...]:
    """The options that give eval / render poses and a size for `name`: its own, or, for a map
    that carries none, those of the SLAM log it was cut from."""
    return () if name in LOGS else ("--poses-from", CORPUS / "slam.mcap")


def assert_same(now: Any, old: Any, where: str = "") -> None:
    """`now` reports every field of `old` with the same value (floats to 1e-9 relative: the
    same numbers, whatever the order of a sum); fields `old` lacks may be added."""
    if isinstance(old, dict):
        assert isinstance(now, dict), where
        for key, value in old.items():
            assert key in now, f"{where}.{key} is no longer reported"
            assert_same(now[key], value, f"{where}.{key}")
    elif isinstance(old, list):
        assert isinstance(now, list) and len(now) == len(old), where
        for i, (a, b) in enumerate(zip(now, old, strict=True)):
            assert_same(a, b, f"{where}[{i}]")
    elif isinstance(old, float) and not isinstance(now, bool):
        assert isinstance(now, (int, float)), where
        assert math.isclose(now, old, rel_tol=1e-9, abs_tol=1e-12), f"{where}: {now} != {old}"
    else:
        assert now == old, f"{where}: {now!r} != {old!r}"


def assert_same_map(now: GaussianMap, old: GaussianMap) -> None:
    """Every array of the two maps equal, bit for bit."""
    for field in fields(GaussianMap):
        np.testing.assert_array_equal(
            getattr(now, field.name), getattr(old, field.name), err_msg=field.name
        )


def test_the_sequence_is_written_again_bit_for_bit(seq: Path) -> None:
    hashes = {
        str(p.relative_to(seq)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(seq.rglob("*"))
        if p.is_file()
    }
    assert hashes == EXPECTED["sequence"]["sha256"]


def test_the_corpus_holds_every_kind_of_file() -> None:
    codecs = {info(name)["map"]["codec"] for name in FILES}
    assert codecs == {"fp32", "fp16", "compact"} and codecs <= set(CODECS)  # none dropped
    assert {"slam.mcap", "pruned.mcap", "merged.mcap", "imported.mcap"} <= set(FILES)
    assert info("interrupted.mcap")["results"]["interrupted"] is True
    assert not info("share_refined.mcap")["map"]["isotropic"]
    assert info("share_keyframes.mcap")["results"]["keyframes"] == 1
    assert sorted(p.name for p in CORPUS.glob("*.mcap")) == FILES


@pytest.mark.parametrize("name", FILES)
def test_info_reports_what_the_earlier_gsc_reported(name: str) -> None:
    r = gsc("info", "--json", CORPUS / name)
    assert r.exit_code == 0, r.output
    assert_same(json.loads(r.output), info(name))
    r = gsc("info", CORPUS / name)
    assert r.exit_code == 0, r.output
    assert f"{gaussians(name)} Gaussians" in r.output


@pytest.mark.parametrize("name", FILES)
def test_export_traj_writes_the_earlier_trajectory(name: str, tmp_path: Path) -> None:
    out = tmp_path / "traj.txt"
    r = gsc("export-traj", CORPUS / name, "-o", out)
    expected = EXPECTED["files"][name]["trajectory"]
    if expected is None:  # a map without poses: refused on one line, as before
        assert r.exit_code == 1 and isinstance(r.exception, SystemExit), r.output
        assert r.output.startswith("Error:") and not out.exists()
        return
    assert r.exit_code == 0, r.output
    assert out.read_text(encoding="utf-8") == expected
    assert len(rows(expected)) == pose_count(name)


@pytest.mark.parametrize("name", FILES)
def test_the_viewer_reads_every_snapshot_and_pose(name: str) -> None:
    from gscompress.view.source import MapSource

    source = MapSource.open(CORPUS / name)
    snapshots = info(name)["snapshots"]
    assert source.snapshot_count == len(snapshots)
    assert [len(source.snapshot(i)) for i in range(len(snapshots))] == [
        s["gaussians"] for s in snapshots
    ]
    assert len(source.poses) == pose_count(name)
    if name in LOGS:
        keyframes = source.keyframes()
        assert keyframes[0] == 0 and set(keyframes) <= set(range(len(source.poses)))


@pytest.mark.parametrize("name", FILES)
def test_export_ply_and_import_ply_keep_every_gaussian(name: str, tmp_path: Path) -> None:
    ply, log = tmp_path / "map.ply", tmp_path / "map.mcap"
    r = gsc("export-ply", CORPUS / name, "-o", ply)
    assert r.exit_code == 0, r.output
    exported = read_ply(ply)
    assert len(exported) == gaussians(name)
    r = gsc("import-ply", ply, "-o", log)
    assert r.exit_code == 0, r.output
    assert_same_map(read_map(log), exported)
    np.testing.assert_array_equal(exported.means, read_map(CORPUS / name).means)


@pytest.mark.parametrize("name", FILES)
def test_prune_keeps_its_fraction_of_every_map(name: str, tmp_path: Path) -> None:
    out = tmp_path / "pruned.mcap"
    r = gsc("prune", CORPUS / name, "--keep", "0.5", "-o", out)
    assert r.exit_code == 0, r.output
    assert len(read_map(out)) == keep_count(gaussians(name), 0.5)


@pytest.mark.parametrize("codec", CODECS)
@pytest.mark.parametrize("name", FILES)
def test_share_cuts_every_map_in_every_codec(name: str, codec: str, tmp_path: Path) -> None:
    out = tmp_path / "share.mcap"
    r = gsc("share", CORPUS / name, out, "--budget", "0.5", "--codec", codec)
    assert r.exit_code == 0, r.output
    assert len(read_map(out)) == keep_count(gaussians(name), 0.5)
    with LogReader(out) as log:
        assert log.read_snapshot().codec == codec


REPLAYED = {
    "pruned.mcap": True,
    "share_compact.mcap": True,
    "share_fp16.mcap": True,
    "share_fp32.mcap": True,
    "share_keyframes.mcap": True,
    "share_refined.mcap": False,
    "merged.mcap": False,
}
"""The corpus files made from others by prune, share and merge: whether the command's result is
exact (no optimisation), or refined (the same Gaussians chosen; their values, refined by torch,
may move with its version)."""


@pytest.mark.parametrize("name", sorted(REPLAYED))
def test_prune_share_and_merge_make_what_the_earlier_gsc_made(
    name: str, seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, threads_restored: None
) -> None:
    # The command as it was recorded, run where it ran (its inputs and `seq` beside it): a byte
    # budget counts the whole file, and the file holds its command line. The earlier gsc
    # counted that text at its length, today's at a fixed size: given the size this text took,
    # today's share is the earlier one.
    with LogReader(CORPUS / name) as log:
        monkeypatch.setattr(cut, "RECORDED_TEXT_BYTES", cut.path_text_bytes(log.metadata))
    argv = shlex.split(info(name)["command"])
    for arg in argv:
        if (CORPUS / arg).is_file() and arg != name:
            shutil.copyfile(CORPUS / arg, tmp_path / arg)
    (tmp_path / "seq").symlink_to(seq)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", argv)
    r = gsc(*argv[1:])
    assert r.exit_code == 0, r.output
    now, old = read_map(tmp_path / name), read_map(CORPUS / name)
    if REPLAYED[name]:
        assert_same_map(now, old)
    else:
        np.testing.assert_array_equal(now.ids, old.ids)
        assert now.log_scales.shape == old.log_scales.shape


@pytest.mark.parametrize("name", FILES)
def test_eval_scores_every_map(name: str, seq: Path) -> None:
    r = gsc("eval", CORPUS / name, "--seq", seq, "--no-lpips", "--json", *views_of(name))
    assert r.exit_code == 0, r.output
    scores = json.loads(r.output)
    assert scores["gaussians"] == gaussians(name)
    assert scores["frames_with_pose"] == pose_count("slam.mcap" if name not in LOGS else name)
    assert math.isfinite(scores["psnr"])
    if "eval" in EXPECTED["files"][name]:
        assert_same(scores, EXPECTED["files"][name]["eval"])


@pytest.mark.parametrize("name", FILES)
def test_render_draws_a_frame_of_every_map(name: str, seq: Path, tmp_path: Path) -> None:
    # (frame 0 is the one merged.mcap carries from its share, which renders leave out)
    r = gsc(
        "render", CORPUS / name, "--seq", seq, "-o", tmp_path, "--frames", "1:2", *views_of(name)
    )
    assert r.exit_code == 0, r.output
    (png,) = tmp_path.rglob("*.png")
    with Image.open(png) as image:
        assert image.size == (32, 24)


@pytest.mark.parametrize("name", FILES)
def test_score_scores_every_gaussian_of_every_map(name: str, seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "scored.mcap"
    r = gsc("score", CORPUS / name, "--seq", seq, "-o", out, "--json")
    assert r.exit_code == 0, r.output
    scored = read_map(out)
    assert len(scored) == gaussians(name) == json.loads(r.output)["scored"]
    assert np.isfinite(scored.importance).all() and scored.importance.max() > 0


MERGES = [
    *(("slam.mcap", share) for share in FILES if share != "slam.mcap"),
    ("merged.mcap", "share_compact.mcap"),
    ("interrupted.mcap", "share_compact.mcap"),
]
"""(receiver, share): slam.mcap receives every other file; the merged and the interrupted logs
receive a share."""


@pytest.mark.parametrize(("receiver", "share"), MERGES)
def test_merge_takes_every_log_as_receiver_and_every_map_as_share(
    receiver: str, share: str, seq: Path, identity: Path, tmp_path: Path
) -> None:
    out = tmp_path / "merged.mcap"
    # an imported map has no world frame: the transform says it is the receiver's
    frame = () if info(share).get("world_frame") else ("--share-transform", identity)
    options = ("--seq", seq, "--iters", "2", "-o", out, "--json", *frame)
    r = gsc("merge", CORPUS / receiver, CORPUS / share, *options)
    assert r.exit_code == 0, r.output
    merged = read_map(out)
    assert 0 < len(merged) <= gaussians(receiver) + gaussians(share)
    assert json.loads(r.output)["gaussians"] == len(merged)
    with LogReader(out) as log:
        assert len(log.read_poses(TOPIC_POSE)[1]) == pose_count(receiver)


ICP_TOLERANCE = 1e-5
"""How far a transform of the builtin ICP may lie from the earlier gsc's, which refined with
Open3D's: the same objective, summed in another order; on the corpus's 38-Gaussian share the
two land 5 micrometres apart."""


@pytest.mark.parametrize("case", EXPECTED["align"], ids=lambda c: f"{c['source']}->{c['target']}")
def test_align_finds_the_earlier_transform(
    case: dict[str, Any], identity: Path, tmp_path: Path
) -> None:
    if not case["init_identity"]:
        pytest.importorskip("open3d", reason="the global step needs Open3D (the [align] extra)")
    out = tmp_path / "T.txt"
    init = ("--init", identity) if case["init_identity"] else ()
    r = gsc("align", CORPUS / case["source"], CORPUS / case["target"], "-o", out, *init)
    assert r.exit_code == 0, r.output
    np.testing.assert_allclose(np.loadtxt(out), case["T_target_source"], rtol=0, atol=ICP_TOLERANCE)


@pytest.mark.parametrize("share", SHARES)
def test_slam_starts_from_every_share(share: str, seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "b.mcap"
    run = ("--preset", "tiny", "--size", WORKING_SIZE, "--frames", "0:2")
    r = gsc("slam", seq, *run, "--inject", CORPUS / share, "-o", out, "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["injected"] == gaussians(share)
    with LogReader(out) as log:
        (step,) = [p["operation"] for p in log.metadata.provenance]
    assert step["name"] == "inject" and step["gaussians"] == gaussians(share)


def test_slam_resumes_the_interrupted_run(seq: Path, tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    shutil.copyfile(CORPUS / "interrupted.mcap", log)
    r = gsc("slam", seq, "-o", log, "--resume", "--json")
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    done = pose_count("interrupted.mcap")
    assert result["resumed_at"] == done and result["frames"] == pose_count("slam.mcap")
    out = tmp_path / "traj.txt"
    assert gsc("export-traj", log, "-o", out).exit_code == 0
    poses = rows(out.read_text(encoding="utf-8"))
    assert len(poses) == pose_count("slam.mcap")
    assert poses[:done] == rows(EXPECTED["files"]["interrupted.mcap"]["trajectory"])
    # the snapshots before the interrupted run's end map stay as they were (the end map is
    # written anew at the real end)
    kept = info("interrupted.mcap")["snapshots"][:-1]
    with LogReader(log) as reader:
        assert len(reader.read_map()) == result["gaussians"] and reader.snapshot_count > len(kept)
        for i, old in enumerate(kept):
            snapshot = reader.read_snapshot(i)
            assert (len(snapshot.gaussians), snapshot.codec) == (old["gaussians"], old["codec"])
