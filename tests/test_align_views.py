"""Refining a map-to-map transform on the target's frames (`gscompress.ops.align_views`): on
frames that are the map's own renders the true transform is the optimum, so a known offset
must be recovered."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from gscompress.camera import quat_to_rotmat
from gscompress.datasets import open_sequence
from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.gaussians import GaussianMap
from gscompress.ops.align import transform_error
from gscompress.ops.align_views import refine_on_views
from gscompress.ops.score import activated_tensors, render_at
from gscompress.slam.densify import gaussians_from_rgbd

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

VIEWS = (11, 12, 13)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[GaussianMap, list, list, object]:
    """A map back-projected from two frames of the synthetic room, and three frames between
    them drawn by the map itself at the true poses (so the identity fits them best)."""
    root = tmp_path_factory.mktemp("align-views")
    sequence = open_sequence(write_synthetic_sequence(root / "room", 40, (64, 48)))
    _, poses = sequence.ground_truth()
    gaussians = GaussianMap.concat(
        [
            gaussians_from_rgbd(
                sequence.frame(i).color,
                sequence.frame(i).depth,
                sequence.intrinsics,
                poses[i],
                opacity=0.95,
                first_id=10_000 * i,
            )
            for i in (10, 14)
        ]
    )
    params = activated_tensors(gaussians)
    frames = []
    for i in VIEWS:
        out = render_at(params, poses[i], sequence.intrinsics)
        depth = torch.where(out.silhouette > 0.5, out.depth_normalized, 0.0)
        frames.append(SimpleNamespace(color=out.color.clamp(0, 1).numpy(), depth=depth.numpy()))
    return gaussians, frames, [poses[i] for i in VIEWS], sequence.intrinsics


def _offset(degrees: float, shift: list[float]) -> np.ndarray:
    axis = np.array([0.2, 1.0, 0.3]) / np.linalg.norm([0.2, 1.0, 0.3])
    half = np.deg2rad(degrees) / 2
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(np.r_[np.cos(half), np.sin(half) * axis])
    T[:3, 3] = shift
    return T


def test_a_known_offset_is_recovered(scene: tuple) -> None:
    gaussians, frames, poses, intrinsics = scene
    T = _offset(2.0, [0.02, -0.01, 0.015])  # 2.7 cm and 2 degrees off
    result = refine_on_views(gaussians, T, frames, poses, intrinsics)
    shift, turn = transform_error(result.T_target_source, np.eye(4))
    assert shift < 0.002 and turn < 0.05, (shift, turn)
    assert result.views == 3 and result.loss_after < result.loss_before
    record = result.record(T)
    assert record["change_cm"] == pytest.approx(100 * transform_error(T, np.eye(4))[0], abs=0.3)
    # from the truth it stays there
    still = refine_on_views(gaussians, np.eye(4), frames, poses, intrinsics)
    shift, turn = transform_error(still.T_target_source, np.eye(4))
    assert shift < 0.002 and turn < 0.05, (shift, turn)


def test_views_that_draw_nothing_of_the_source_leave_the_transform(scene: tuple) -> None:
    gaussians, frames, poses, intrinsics = scene
    away = [pose @ _offset(180.0, [0.0, 0.0, 0.0]) for pose in poses]  # (turned around)
    T = _offset(1.0, [0.01, 0.0, 0.0])
    result = refine_on_views(gaussians, T, frames, away, intrinsics)
    assert result.views == 0 and np.array_equal(result.T_target_source, T)


def test_gsc_align_refines_on_the_targets_frames(run: dict[str, Path], tmp_path: Path) -> None:
    """`gsc align --seq` on a log aligned to itself: the tiny run's 48x36 map is too coarse to
    draw its own frames well, and the frames would pull it off its own surfaces, so the
    registration's transform (the identity) is kept, and the file and the report say so."""
    pytest.importorskip("open3d", reason="the aligner needs Open3D: pip install '.[align]'")
    from click.testing import CliRunner

    from gscompress.io.trajectory import read_transform
    from gscompress_cli.main import cli

    out = tmp_path / "T.txt"
    args = ["align", str(run["log"]), str(run["log"]), "-o", str(out), "--seq", str(run["seq"])]
    r = CliRunner().invoke(cli, [*args, "--json"])
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    on_frames = result["on_frames"]
    assert on_frames["views"] >= 1 and on_frames["loss_after"] < on_frames["loss_before"]
    assert on_frames["kept_registration"] and on_frames["surface_kept"] < 0.8
    assert on_frames["change_cm"] > 1.0  # (where the frames would have taken it)
    np.testing.assert_allclose(read_transform(out), result["T_target_source"], atol=1e-9)
    np.testing.assert_allclose(read_transform(out), on_frames["T_registration"], atol=1e-9)
    shift, turn = transform_error(read_transform(out), np.eye(4))
    assert shift < 0.005 and turn < 0.5
    assert "kept the registration" in out.read_text()
    r = CliRunner().invoke(cli, [*args, "--force"])
    assert r.exit_code == 0 and "kept the registration" in r.output


def test_an_alignment_reports_its_registration_and_each_iteration_on_the_frames(
    run: dict[str, Path], tmp_path: Path
) -> None:
    """`gsc align`'s bar: the registration as it starts, then each iteration on the frames."""
    from gscompress.ops.align_views import VIEW_ALIGN
    from gscompress.pipeline.aligning import ON_FRAMES, REGISTRATION, align_logs_transform

    guess = tmp_path / "guess.txt"
    np.savetxt(guess, np.eye(4))
    events: list[tuple[str, int, int | None]] = []
    align_logs_transform(
        run["log"],
        run["log"],
        init=guess,
        seq=run["seq"],
        refuse=False,
        phases=lambda *event: events.append(event),
    )
    assert events[0] == (REGISTRATION, 0, None)
    on_frames = [e for e in events if e[0] == ON_FRAMES]
    assert on_frames[0] == (ON_FRAMES, 0, VIEW_ALIGN.iters) and len(on_frames) > 10
    assert [e[1] for e in on_frames] == list(range(len(on_frames)))
