"""The synthetic room: determinism, exact depth, trackable texture, and `gsc synth`."""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from gscompress.datasets import open_sequence
from gscompress.datasets.synthetic import (
    CEILING,
    FLOOR,
    ROOM_MAX,
    synthetic_sequence,
    write_synthetic_sequence,
    writer_threads,
)
from gscompress.errors import OutputError
from gscompress_cli.main import cli


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_same_seed_same_bytes_other_seed_other_scene(tmp_path: Path) -> None:
    a = write_synthetic_sequence(tmp_path / "a", frames=4, size=(48, 36), seed=5)
    b = write_synthetic_sequence(tmp_path / "b", frames=4, size=(48, 36), seed=5)
    c = write_synthetic_sequence(tmp_path / "c", frames=4, size=(48, 36), seed=6)
    da, db, dc = _digest(a), _digest(b), _digest(c)
    assert da == db and len(da) == 4 + 4 + 4  # rgb, depth, 4 text/json files
    assert da["rgb/000000.png"] != dc["rgb/000000.png"]


def test_floor_and_ceiling_depth_is_exact() -> None:
    seq = synthetic_sequence(40, (64, 48), seed=0)
    K = seq.intrinsics
    checked = 0
    for i in (0, 17, 39):
        frame, surface = seq.render_with_surfaces(i)
        T = frame.T_world_cam
        u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
        d_world = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1)
        d_world = d_world @ T[:3, :3].T
        cam_z = T[2, 3]
        # a ray o + s d with unit camera-z reaches the plane z = h at s = depth = (h - o_z) / d_z
        for sid, height in ((FLOOR, 0.0), (CEILING, ROOM_MAX[2])):
            m = surface == sid
            expected = (height - cam_z) / d_world[..., 2][m]
            np.testing.assert_allclose(frame.depth[m], expected, rtol=2e-7)
            checked += int(m.sum())
    assert checked > 1000


def test_frames_are_textured_everywhere() -> None:
    seq = synthetic_sequence(60, (160, 120), seed=0)
    for i in (0, 30, 59):
        f = seq.frame(i)
        assert np.all(f.depth > 0.3) and np.all(f.depth < 8.0)
        grey = f.color.mean(axis=-1)
        gx = np.abs(np.diff(grey, axis=1))[:-1, :]
        gy = np.abs(np.diff(grey, axis=0))[:, :-1]
        grad = np.maximum(gx, gy)
        # every 16x16 block has visible texture (no flat, untrackable regions)
        blocks = grad[:112, :144].reshape(7, 16, 9, 16).max(axis=(1, 3))
        assert blocks.min() > 0.02
    # the camera moves and turns
    _, poses = seq.ground_truth()
    assert np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3]) > 0.5
    cos = (np.trace(poses[0, :3, :3].T @ poses[-1, :3, :3]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) > 20


def test_refuses_non_empty_output_and_force_replaces_only_a_sequence(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "seq"
    write_synthetic_sequence(out, frames=3, size=(16, 12))
    with pytest.raises(OutputError, match="not empty"):
        write_synthetic_sequence(out, frames=2, size=(16, 12))
    write_synthetic_sequence(out, frames=2, size=(16, 12), force=True)  # an earlier sequence
    assert len(open_sequence(out)) == 2
    (out / "notes.txt").write_text("x")  # someone else's file: --force must not delete it
    with pytest.raises(OutputError, match=r"notes\.txt"):
        write_synthetic_sequence(out, frames=2, size=(16, 12), force=True)
    assert (out / "notes.txt").exists() and len(open_sequence(out)) == 2
    (out / "notes.txt").unlink()
    for kept in (out / "rgb" / "README.txt", out / "depth" / "originals" / "raw.png"):
        kept.parent.mkdir(exist_ok=True)
        kept.write_text("x")  # nested in the frame folders, and not in the listings
        with pytest.raises(OutputError, match="does not list"):
            write_synthetic_sequence(out, frames=2, size=(16, 12), force=True)
        assert kept.exists()
        if kept.parent.name == "originals":
            shutil.rmtree(kept.parent)
        else:
            kept.unlink()
    link = tmp_path / "link"
    link.symlink_to(out)
    with pytest.raises(OutputError, match="is a link"):
        write_synthetic_sequence(link, frames=2, size=(16, 12), force=True)
    link.unlink()
    write_synthetic_sequence(out, frames=3, size=(16, 12), force=True)  # clean again: replaced
    assert len(open_sequence(out)) == 3
    monkeypatch.chdir(out)  # the folder the user is in cannot be swapped out from under them
    with pytest.raises(OutputError, match="current folder"):
        write_synthetic_sequence(".", frames=2, size=(16, 12), force=True)
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]  # no temporary folders left


def test_gsc_synth_command(tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "demo"
    result = runner.invoke(cli, ["synth", str(out), "--frames", "3", "--size", "32x24"])
    assert result.exit_code == 0, result.output
    assert "wrote 3 frames (32x24)" in result.output
    for name in (
        "rgb.txt",
        "depth.txt",
        "groundtruth.txt",
        "intrinsics.json",
        "rgb/000002.png",
        "depth/000002.png",
    ):
        assert (out / name).is_file()
    seq = open_sequence(out)
    assert len(seq) == 3 and seq.intrinsics.width == 32 and seq.has_ground_truth

    again = runner.invoke(cli, ["synth", str(out), "--frames", "3", "--size", "32x24"])
    assert again.exit_code == 1 and "not empty" in again.output
    forced = runner.invoke(cli, ["synth", str(out), "--frames", "2", "--size", "32x24", "--force"])
    assert forced.exit_code == 0 and len(open_sequence(out)) == 2
    bad = runner.invoke(cli, ["synth", str(tmp_path / "x"), "--size", "32by24"])
    assert bad.exit_code == 2 and "WxH" in bad.output


def test_supersampling_changes_colour_only() -> None:
    one = synthetic_sequence(frames=2, size=(64, 48), supersample=1).frame(1)
    four = synthetic_sequence(frames=2, size=(64, 48), supersample=2).frame(1)
    np.testing.assert_array_equal(one.depth, four.depth)
    assert not np.array_equal(one.color, four.color)
    # averaging 2x2 samples smooths the texture: less pixel-to-pixel variation
    assert np.abs(np.diff(four.color, axis=1)).mean() < np.abs(np.diff(one.color, axis=1)).mean()


def test_synth_writes_with_as_many_threads_as_gsc_threads(tmp_path, monkeypatch, threads_restored):
    from gscompress.datasets import synthetic

    monkeypatch.setenv("OMP_NUM_THREADS", "9")
    assert writer_threads() == 4  # capped
    monkeypatch.setenv("OMP_NUM_THREADS", "junk")
    assert writer_threads() == min(4, os.cpu_count() or 1)
    used = []
    real = synthetic.write_tum_sequence
    monkeypatch.setattr(
        synthetic, "write_tum_sequence", lambda *a, **k: used.append(k["workers"]) or real(*a, **k)
    )
    args = ["--threads", "1", "synth", str(tmp_path / "s"), "--frames", "2", "--size", "16x12"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    assert used == [1]


@pytest.mark.slow
def test_sigterm_ends_synth_with_130_and_leaves_no_temporary_folder(
    tmp_path: Path, terminated: Any
) -> None:
    """SIGTERM while frames are being written: exit code 130 as on Ctrl-C, one line saying so,
    and neither the sequence nor its hidden temporary folder is left behind."""
    out = tmp_path / "room"
    cmd = [
        sys.executable,
        "-m",
        "gscompress_cli",
        "synth",
        str(out),
        "--frames",
        "2000",
        "--size",
        "64x48",
    ]

    def writing(stderr: str) -> bool:  # a frame is in the temporary folder
        return any(tmp.glob("rgb/*.png") for tmp in tmp_path.glob(".room.*.tmp"))

    code, stderr = terminated(cmd, writing)
    assert code == 130 and "Interrupted" in stderr.splitlines()[-1], stderr
    assert list(tmp_path.iterdir()) == []


def test_huge_or_conflicting_values_are_usage_errors(tmp_path: Path) -> None:
    for args, says in (
        (["--frames", "9223372036854775808"], "not in the range 1<=x<=100000"),
        (["--size", "4x4"], "at least 8x8"),
        (["--size", "9000x10"], "at most 8192 pixels per side"),
    ):
        r = CliRunner().invoke(cli, ["synth", str(tmp_path / "x"), *args])
        assert r.exit_code == 2 and says in r.output and "synth --help" in r.output, r.output
    assert list(tmp_path.iterdir()) == []


def test_an_interrupt_that_surfaces_as_another_error_still_ends_with_130() -> None:
    """SIGTERM's KeyboardInterrupt can land inside a library's lock code and come out as a
    RuntimeError ("release unlocked lock", seen in a thread pool): that is the interrupt, so
    the command ends as interrupted. The same error with no signal stays an error."""
    import signal

    import click

    from gscompress_cli.main import GscGroup

    @click.command()
    @click.option("--signal/--no-signal", "send", default=True)
    def boom(send: bool) -> None:
        try:
            if send:
                os.kill(os.getpid(), signal.SIGTERM)
                signal.sigtimedwait([], 5.0)  # (the handler runs here)
        except KeyboardInterrupt:
            pass
        raise RuntimeError("release unlocked lock")

    class Group(GscGroup):
        def get_command(self, ctx: Any, cmd_name: str) -> click.Command | None:
            return boom if cmd_name == "boom" else None

    result = CliRunner().invoke(Group(), ["boom"])
    assert result.exit_code == 130, result.output
    assert "Interrupted" in result.output
    plain = CliRunner().invoke(Group(), ["boom", "--no-signal"])
    assert plain.exit_code == 1 and isinstance(plain.exception, RuntimeError)
