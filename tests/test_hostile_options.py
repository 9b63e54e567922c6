"""Options, config files and paths a user can get wrong: one line of error, nothing lost."""

from __future__ import annotations

import errno
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gscompress.camera import quat_to_rotmat
from gscompress.datasets.base import parse_frames, parse_size
from gscompress.datasets.recording import RecordingOptions
from gscompress.errors import (
    DatasetError,
    GscError,
    InputError,
    MapError,
    OptionError,
    OutputError,
)
from gscompress.gaussians import random_map
from gscompress.io import files
from gscompress.io.files import check_output, read_text
from gscompress.io.trajectory import read_transform
from gscompress.ops.merge import MergeOptions, transform_map
from gscompress.pipeline.experiment.protocol import ExperimentSettings
from gscompress.pipeline.experiment.run import check_executor
from gscompress.pipeline.slam_run import refuse_own_settings
from gscompress.slam.config import load_config, resolve_config
from gscompress_cli.flags import with_flags
from gscompress_cli.main import cli


def test_an_output_that_is_a_fifo_is_refused_even_with_force(tmp_path: Path) -> None:
    fifo = tmp_path / "out.mcap"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="not a regular file"):
        check_output(fifo, force=True)
    assert fifo.is_fifo()  # (a rename over it would have replaced it, as it did /dev/null)


def test_a_dropped_output_leaves_no_temporary_file_even_when_closing_fails(
    tmp_path: Path,
) -> None:
    out = files.AtomicFile(tmp_path / "a.ply")
    out.file.write(b"x")

    class FullDisk:
        def close(self) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

    real, out.file = out.file, FullDisk()  # type: ignore[assignment]
    out.discard()
    real.close()
    assert list(tmp_path.iterdir()) == []


def test_text_inputs_are_read_up_to_a_sane_size(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="/dev/zero is over 64 MiB"):  # (not read to the end)
        read_text("/dev/zero", "trajectory")
    huge = tmp_path / "huge.yaml"
    huge.write_text("tracking: {rho: [" + "1," * 600_000 + "1]}\n")  # 1.2 MB of list items
    with pytest.raises(InputError, match=r"config file .* is over 1 MiB"):
        load_config(huge)
    with pytest.raises(DatasetError, match="is a directory"):
        read_text(tmp_path, "intrinsics", DatasetError)
    with pytest.raises(InputError, match="file not found"):
        read_text(tmp_path / "nope.txt", "transform")
    big = tmp_path / "big.txt"
    big.write_text("0 " * 1024)
    with pytest.raises(InputError, match="over 1 KiB: too large for a trajectory file"):
        read_text(big, "trajectory", limit=1024)
    small = tmp_path / "ok.txt"
    small.write_text("1 2\n")
    assert read_text(small, "trajectory") == "1 2\n"


@pytest.mark.parametrize(
    "text, message",
    [
        # nine levels of nine aliases: a full repr of the value would have 9^9 items
        (
            "tracking: {rho: [&a0 [x, x, x, x, x, x, x, x, x], "
            + ", ".join(f"&a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 9))
            + "]}\n",
            "tracking.rho: expected a finite number, got",
        ),
        ("seed: " + "9" * 5000 + "\n", "cannot read config"),
        ("a: " + "[" * 20000 + "]" * 20000 + "\n", "cannot read config"),
        ("size: " + "9" * 5000 + "x8\n", "expected WxH"),
        ("mapping: {lr_means: " + "9" * 400 + "}\n", "expected a finite number"),
    ],
)
def test_configs_that_would_blow_up_are_refused_in_one_short_line(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as caught:
        load_config(path)
    assert len(str(caught.value)) < 400 and "\n" not in str(caught.value)


def test_frame_indices_too_long_for_int_are_refused() -> None:
    with pytest.raises(InputError, match="over 18 digits"):
        parse_frames("9" * 5000 + ":")
    assert parse_frames("3:" + "9" * 18).start == 3


def test_a_quaternion_too_long_to_take_the_norm_of_still_gives_its_rotation(
    tmp_path: Path,
) -> None:
    path = tmp_path / "t.txt"
    path.write_text("0 0 0 1e300 1e300 0 0\n")  # 180 degrees about (1, 1, 0)
    expected = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]])
    np.testing.assert_allclose(read_transform(path)[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(np.array([0, 1e300, 1e300, 0])), expected, atol=1e-12)


def test_a_transform_that_moves_gaussians_out_of_float32_range_is_refused() -> None:
    T = np.eye(4)
    T[0, 3] = 1e39
    with pytest.raises(MapError, match="beyond the float32 range"):
        transform_map(random_map(10, seed=0), T)


@pytest.mark.parametrize(
    "raised, said",
    [
        (MemoryError(), "Error: out of memory"),
        (RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried"), "out of memory"),
        (RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"), "out of memory"),
        (OSError(errno.ENOSPC, "No space left on device", ".a.ply.123.tmp"), "a.ply: No space"),
    ],
)
def test_running_out_of_memory_or_disk_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, raised: BaseException, said: str
) -> None:
    _synth_raises(monkeypatch, raised)
    r = CliRunner().invoke(cli, ["synth", str(tmp_path / "s"), "--frames", "2"])
    assert r.exit_code == 1 and r.output.startswith("Error: ") and said in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1


def test_a_runtime_error_that_is_not_about_memory_is_still_a_bug(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _synth_raises(monkeypatch, RuntimeError("shapes do not match"))
    r = CliRunner().invoke(cli, ["synth", str(tmp_path / "s"), "--frames", "2"])
    assert isinstance(r.exception, RuntimeError)  # (its traceback is shown)


def _synth_raises(monkeypatch: pytest.MonkeyPatch, raised: BaseException) -> None:
    import gscompress_cli.synth as synth

    def fail(*args: object, **kwargs: object) -> None:
        raise raised

    monkeypatch.setattr(synth, "write_synthetic_sequence", fail)


@pytest.mark.parametrize(
    "fields, message",
    [
        ('"width": 1e400', "size must be positive"),  # (JSON reads it as infinity)
        ('"width": 1e20', "width and height are whole"),
        ('"width": 64.5', "width and height are whole"),
        ('"fx": ' + "9" * 4000, "bad value"),  # an int beyond float range
        ('"fx": ' + "9" * 5000, "cannot read intrinsics"),  # beyond int() of a string
        ('"depth_scale": true', "bad value"),
        ('"fx": 1e-320', "in pixels, at least 1"),  # (subnormal: numpy warned, then diverged)
        ('"fy": 0.78', "normalised intrinsics"),
    ],
)
def test_intrinsics_beyond_what_a_camera_has_are_refused(
    tmp_path: Path, fields: str, message: str
) -> None:
    from gscompress.datasets.base import read_intrinsics_file

    values = {"fx": "50", "fy": "50", "cx": "32", "cy": "24", "width": "64", "height": "48"}
    body = ", ".join(f'"{k}": {v}' for k, v in values.items() if f'"{k}"' not in fields)
    path = tmp_path / "intrinsics.json"
    path.write_text("{" + body + ", " + fields + "}")
    with pytest.raises(DatasetError, match=message):
        read_intrinsics_file(path)


def test_an_output_that_is_a_symbolic_link_is_refused(tmp_path: Path) -> None:
    link = tmp_path / "out.yaml"
    link.symlink_to("/proc/self/fd/1")  # a regular file whenever stdout is redirected
    for output in (link, Path("/dev/stdout")):  # the rename would replace the link
        with pytest.raises(OutputError, match="is a symbolic link"):
            check_output(output, force=True)


def test_a_config_can_come_through_a_pipe(tmp_path: Path) -> None:
    read, write = os.pipe()
    os.write(write, b"preset: tiny\nseed: 7\n")
    os.close(write)
    try:
        assert load_config(f"/dev/fd/{read}").seed == 7
    finally:
        os.close(read)


@pytest.mark.parametrize("text", ["\u00b2x3", "\u0663\u0662\u0660x240", "320x\uff12\uff14\uff10"])
def test_a_size_in_other_digits_is_refused_alike_on_the_command_line_and_in_a_config(
    tmp_path: Path, text: str
) -> None:
    assert parse_size(text) is None
    path = tmp_path / "c.yaml"
    path.write_text(f'size: "{text}"\n', encoding="utf-8")
    with pytest.raises(InputError, match="expected WxH"):
        load_config(path)
    result = CliRunner().invoke(cli, ["synth", str(tmp_path / "seq"), "--size", text])
    assert result.exit_code == 2 and "is not a size WxH" in result.output
    assert not (tmp_path / "seq").exists()
    assert parse_size(" 320 X 240 ") == (320, 240)


def test_a_diverging_run_says_so_in_one_line_without_resume_advice(tmp_path: Path) -> None:
    from gscompress.datasets.synthetic import write_synthetic_sequence

    seq = write_synthetic_sequence(tmp_path / "room", 3, (32, 24))
    config = tmp_path / "c.yaml"
    config.write_text("preset: tiny\nmapping: {lr_log_scales: 1000.0}\n")
    r = CliRunner().invoke(cli, ["slam", str(seq), "--config", str(config), "-o", "x.mcap"])
    assert r.exit_code == 1, r.output
    assert r.output.startswith("Error: mapping diverged (") and "--resume" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_a_merge_whose_refinement_diverges_says_how_to_merge_anyway(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import torch

    from gscompress.camera import Intrinsics
    from gscompress.errors import DivergenceError
    from gscompress.ops.refine import refine
    from gscompress.slam.config import preset
    from gscompress.slam.keyframes import View
    from gscompress.slam.mapper import TOO_HIGH, Mapper

    def diverging(*args: object, **kwargs: object) -> None:
        raise DivergenceError("mapping", "its loss became nan", TOO_HIGH)

    monkeypatch.setattr(Mapper, "refine", diverging)
    view = View(0, torch.zeros(24, 32, 3), torch.ones(24, 32), np.eye(4))
    intrinsics = Intrinsics(30.0, 30.0, 16.0, 12.0, 32, 24)
    with pytest.raises(DivergenceError, match=r"refinement diverged \(its loss .*`iters` 0"):
        refine(random_map(5, seed=0), [view], intrinsics, preset("tiny"), 3)


@pytest.mark.parametrize("digits", [300, 5000])
def test_a_huge_number_for_an_integer_option_is_echoed_clipped(tmp_path: Path, digits: int) -> None:
    result = CliRunner().invoke(cli, ["synth", str(tmp_path / "s"), "--frames", "9" * digits])
    assert result.exit_code == 2
    assert f"({digits} digits)" in result.output and len(result.output) < 300
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("name", ["newdir/", "newdir/.", ""])
def test_an_output_named_as_a_folder_or_empty_is_refused(tmp_path: Path, name: str) -> None:
    log = tmp_path / "a.mcap"
    from gscompress.io.mcap_log import LogMetadata, LogWriter

    with LogWriter(log, LogMetadata()) as out:
        out.write_gaussians(random_map(10), 0)
    before = set(tmp_path.iterdir())
    for args in (["prune", str(log), "--keep", "0.5", "-o"], ["export-ply", str(log), "-o"]):
        r = CliRunner().invoke(cli, [*args, f"{tmp_path}/{name}" if name else ""])
        assert r.exit_code == 2, r.output
        assert ("names a folder" if name else "an empty path names no file") in r.output
    assert set(tmp_path.iterdir()) == before


def _refused(call: Callable[[], object]) -> GscError:
    with pytest.raises(GscError) as caught:
        call()
    return caught.value


@pytest.mark.parametrize(
    ("call", "on_the_command_line"),
    [
        (
            lambda: resolve_config("tiny", keep=0.5, no_prune=True),
            "--keep does not go with --no-prune: there is no pruning stage",
        ),
        (lambda: MergeOptions(margin=0.5).check(), "--margin must be >= 1, got 0.5"),
        (
            lambda: RecordingOptions(max_dt=2.0),
            "--max-dt must be above 0 and at most 1 s, got 2.0",
        ),
        (lambda: RecordingOptions(camera_info=" "), "--camera-info must name a topic"),
        (
            lambda: check_executor("local", 1, "ray://head:10001", None),
            "--address and --cpus-per-run are for --executor ray",
        ),
        (
            lambda: ExperimentSettings(seeds=2, sweep_seeds=3).check(),
            "--sweep-seeds 3 is more than --seeds 2: the sweep runs on the first seeds",
        ),
        (
            lambda: refuse_own_settings(
                (None, None, "0:4", None, None, None, None, None), True, None
            ),
            "--resume continues with the log's own settings; drop --frames, --no-prune",
        ),
    ],
)
def test_a_library_error_names_no_flag(
    call: Callable[[], object], on_the_command_line: str
) -> None:
    """The library speaks of its parameters (`name`); gsc shows each as its flag (--name)."""
    refused = _refused(call)
    assert "--" not in str(refused)
    assert with_flags(refused) == on_the_command_line


def test_a_library_error_names_its_parameters_and_gsc_shows_them_as_flags(tmp_path: Path) -> None:
    with pytest.raises(OptionError) as caught:
        MergeOptions(share_rate=2.0).check()
    assert str(caught.value) == "`share_rate` must be in [0, 1], got 2.0"
    assert with_flags(caught.value) == "--share-rate must be in [0, 1], got 2.0"
    log, other = (Path(__file__).parent / "corpus" / name for name in ("slam.mcap", "pruned.mcap"))
    poses = tmp_path / "poses.txt"
    poses.write_text("")
    args = ["eval", log, "--seq", tmp_path, "--poses", poses, "--poses-from", other]
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert r.exit_code == 2
    assert "Error: --poses and --poses-from do not go together: give one source" in r.output
