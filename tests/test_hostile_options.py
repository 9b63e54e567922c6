"""Options, config files and paths a user can get wrong: one line of error, nothing lost."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gscompress.camera import quat_to_rotmat
from gscompress.datasets.base import parse_frames
from gscompress.errors import DatasetError, InputError, MapError, OutputError
from gscompress.gaussians import random_map
from gscompress.io import files
from gscompress.io.files import check_output, read_text
from gscompress.io.trajectory import read_transform
from gscompress.ops.merge import transform_map
from gscompress.slam.config import load_config
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


def test_text_inputs_must_be_regular_files_of_a_sane_size(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fifo = tmp_path / "c.yaml"
    os.mkfifo(fifo)  # reading it would wait forever; /dev/zero would fill the memory
    with pytest.raises(InputError, match=r"c\.yaml is not a regular file"):
        read_text(fifo, "config")
    with pytest.raises(DatasetError, match="is a directory"):
        read_text(tmp_path, "intrinsics", DatasetError)
    with pytest.raises(InputError, match="file not found"):
        read_text(tmp_path / "nope.txt", "transform")
    big = tmp_path / "big.txt"
    big.write_text("0 " * 100)
    monkeypatch.setattr(files, "MAX_TEXT_BYTES", 100)
    with pytest.raises(InputError, match="too large"):
        read_text(big, "trajectory")
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
        (OSError("1589 requested and 738 written"), "input/output error: 1589 requested"),
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
