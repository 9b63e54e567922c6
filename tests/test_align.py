"""`gsc align` and `gscompress.ops.align`: transforms between maps recovered from constructed
scenes with a known transform (noise, partial overlap, outliers), and scenes that must be
refused (too little overlap, symmetric, degenerate)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from gscompress.errors import MissingDependencyError
from gscompress.gaussians import GaussianMap
from gscompress.io.mcap_log import LogMetadata, LogReader, LogWriter
from gscompress.io.trajectory import read_transform
from gscompress.ops.align import (
    FINE_STAGES,
    AlignmentError,
    AlignOptions,
    Cloud,
    align_clouds,
    map_cloud,
    refine_alignment,
    transform_error,
    transform_points,
)
from gscompress.ops.icp import ICP, grid_cloud
from gscompress_cli.main import cli

try:
    import open3d  # noqa: F401
except ImportError:
    HAS_OPEN3D = False
else:
    HAS_OPEN3D = True
needs_open3d = pytest.mark.skipif(
    not HAS_OPEN3D, reason="the global step needs Open3D: pip install 'gscompress[align]'"
)
"""The tests of the global step (no initial guess); the local step runs without Open3D."""

SPACING = 0.04


def _grid(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.meshgrid(u, v)
    return a.ravel(), b.ravel()


def _box(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Points on the five visible faces (no bottom) of an axis-aligned box."""
    faces = []
    for axis in range(3):
        others = [i for i in range(3) if i != axis]
        u = np.arange(lo[others[0]], hi[others[0]] + 1e-9, spacing)
        v = np.arange(lo[others[1]], hi[others[1]] + 1e-9, spacing)
        a, b = _grid(u, v)
        for value in (lo[axis], hi[axis]):
            if axis == 2 and value == lo[axis]:
                continue
            face = np.empty((len(a), 3))
            face[:, axis], face[:, others[0]], face[:, others[1]] = value, a, b
            faces.append(face)
    return np.concatenate(faces)


def room(spacing: float = SPACING, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A corner of a room, 2.4 x 2 m: floor, two walls, three boxes and a ball, textured.

    Returns:
        points [N, 3] and colours [N, 3].
    """
    rng = np.random.default_rng(seed)
    s = np.arange(0.0, 2.4, spacing)
    t = np.arange(0.0, 2.0, spacing)
    h = np.arange(0.0, 1.2, spacing)
    parts = []
    a, b = _grid(s, t)
    parts.append(np.stack([a, b, np.zeros_like(a)], 1))  # floor
    a, b = _grid(s, h)
    parts.append(np.stack([a, np.zeros_like(a), b], 1))  # wall y = 0
    a, b = _grid(t, h)
    parts.append(np.stack([np.zeros_like(a), a, b], 1))  # wall x = 0
    parts.append(_box(np.array([0.4, 0.4, 0.0]), np.array([0.7, 0.7, 0.35]), spacing))
    parts.append(_box(np.array([1.0, 0.3, 0.0]), np.array([1.3, 0.5, 0.5]), spacing))
    parts.append(_box(np.array([1.7, 1.1, 0.0]), np.array([1.9, 1.6, 0.6]), spacing))
    d = rng.normal(size=(400, 3))
    parts.append(np.array([1.3, 1.2, 0.25]) + 0.2 * d / np.linalg.norm(d, axis=1, keepdims=True))
    points = np.concatenate(parts)
    colors = 0.5 + 0.4 * np.stack(
        [np.sin(9 * points[:, 0]), np.cos(7 * points[:, 1]), np.sin(8 * points[:, 2] + 1)], 1
    )
    return points, colors


def random_transform(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.uniform(-1.0, 1.0, 3) * np.pi / 2).as_matrix()
    T[:3, 3] = rng.uniform(-2.0, 2.0, 3)
    return T


def agents(
    points: np.ndarray,
    colors: np.ndarray,
    T_target_source: np.ndarray,
    *,
    source_part: np.ndarray,
    target_part: np.ndarray,
    noise: float = 0.0,
    outliers: float = 0.0,
    seed: int = 1,
) -> tuple[Cloud, Cloud]:
    """Source and target clouds of the parts of a scene, the source in a frame of its own."""
    rng = np.random.default_rng(seed)

    def cloud(mask: np.ndarray, T: np.ndarray) -> Cloud:
        pts = points[mask] + rng.normal(scale=noise, size=(int(mask.sum()), 3))
        col = colors[mask]
        k = int(outliers * len(pts))
        if k:
            lo, hi = points.min(0), points.max(0)
            pts = np.concatenate([pts, rng.uniform(lo, hi, (k, 3))])
            col = np.concatenate([col, rng.uniform(0, 1, (k, 3))])
        return Cloud(transform_points(T, pts), col, viewpoints=transform_points(T, VIEWS))

    return cloud(source_part, np.linalg.inv(T_target_source)), cloud(target_part, np.eye(4))


VIEWS = np.array([[1.2, 1.0, 0.8], [1.8, 1.5, 0.9], [0.8, 1.6, 0.9]])


@needs_open3d
@pytest.mark.parametrize(
    ("noise", "outliers", "split"),
    [(0.0, 0.0, 1.0), (0.005, 0.0, 1.0), (0.005, 0.1, 1.0), (0.005, 0.05, 0.6)],
    ids=["exact", "noise", "outliers", "partial"],
)
def test_recovers_a_known_transform(noise: float, outliers: float, split: float) -> None:
    points, colors = room()
    T = random_transform(3)
    lo, hi = 2.4 * (1.0 - split), 2.4 * split  # (split 1: both see everything)
    source, target = agents(
        points,
        colors,
        T,
        source_part=points[:, 0] <= hi + 1e-9,
        target_part=points[:, 0] >= lo - 1e-9,
        noise=noise,
        outliers=outliers,
    )
    result = align_clouds(source, target)
    dt, dr = transform_error(result.T_target_source, T)
    assert dt < 0.01 and dr < 0.5, (dt, dr)
    assert result.refused == "" and result.global_step == "ransac-fpfh"
    assert result.inliers is not None and result.inliers >= 12
    assert result.ambiguity < 0.85 and result.conditioning > 0.02
    assert result.residual < max(2.0 * noise, 0.002) + 0.01
    if split < 1.0:  # the share of each map on the other: about 0.2 / 0.6 of the room's length
        assert 0.2 < result.source_overlap < 0.8 and 0.2 < result.target_overlap < 0.8
    else:
        assert result.overlap > 0.8


def test_refinement_from_a_guess_and_refine_alignment() -> None:
    points, colors = room()
    T = random_transform(5)
    everything = np.ones(len(points), bool)
    source, target = agents(
        points, colors, T, source_part=everything, target_part=everything, noise=0.003
    )
    nudge = np.eye(4)
    nudge[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.radians(3.0)]).as_matrix()
    nudge[:3, 3] = [0.04, -0.03, 0.02]
    guess = nudge @ T
    result = align_clouds(source, target, init=guess)
    assert result.global_step == "init" and result.inliers is None
    assert max(transform_error(result.T_target_source, T)[0], 0) < 0.01
    local = refine_alignment(source, target, guess)
    np.testing.assert_allclose(local.T_target_source, result.T_target_source, atol=1e-9)
    assert transform_error(guess, T)[0] > 0.04  # (the guess was off: refining moved it)


@needs_open3d
def test_too_little_overlap_is_refused() -> None:
    points, colors = room()
    T = random_transform(7)
    source, target = agents(
        points, colors, T, source_part=points[:, 0] < 0.9, target_part=points[:, 0] > 1.5
    )
    with pytest.raises(AlignmentError, match="overlap") as caught:
        align_clouds(source, target)
    assert "\n" not in str(caught.value)
    assert caught.value.alignment is not None
    assert caught.value.alignment.refused == str(caught.value)


def _symmetric_room(spacing: float = SPACING) -> tuple[np.ndarray, np.ndarray]:
    """An empty 2 x 3 m room, floor and four walls, one colour: a half turn maps it onto
    itself."""
    s, t, h = (np.arange(0.0, x + 1e-9, spacing) for x in (2.0, 3.0, 1.0))
    parts = []
    a, b = _grid(s, t)
    parts.append(np.stack([a, b, np.zeros_like(a)], 1))
    for y in (0.0, 3.0):
        a, b = _grid(s, h)
        parts.append(np.stack([a, np.full_like(a, y), b], 1))
    for x in (0.0, 2.0):
        a, b = _grid(t, h)
        parts.append(np.stack([np.full_like(a, x), a, b], 1))
    points = np.concatenate(parts)
    return points, np.full_like(points, 0.6)


def _plane(spacing: float = SPACING) -> tuple[np.ndarray, np.ndarray]:
    """A 2 x 2 m floor of one colour: it slides and turns in itself."""
    s = np.arange(0.0, 2.0, spacing)
    a, b = _grid(s, s)
    points = np.stack([a, b, np.zeros_like(a)], 1)
    return points, np.full_like(points, 0.5)


@needs_open3d
@pytest.mark.parametrize("scene", [_symmetric_room, _plane], ids=["symmetric-room", "plane"])
def test_symmetric_and_flat_scenes_are_refused(
    scene: Callable[[], tuple[np.ndarray, np.ndarray]],
) -> None:
    points, colors = scene()
    everything = np.ones(len(points), bool)
    source, target = agents(
        points,
        colors,
        random_transform(11),
        source_part=everything,
        target_part=everything,
        noise=0.003,
    )
    with pytest.raises(AlignmentError, match=r"ambiguous|degenerate"):
        align_clouds(source, target)


def test_bad_inputs_and_options() -> None:
    points, colors = room()
    few = Cloud(points[:10], colors[:10])
    with pytest.raises(AlignmentError, match="10 opaque Gaussians"):
        align_clouds(few, Cloud(points, colors))
    with pytest.raises(Exception, match="min_overlap"):
        align_clouds(few, few, AlignOptions(min_overlap=2.0))
    with pytest.raises(Exception, match=r"colors must be \[3, 3\]"):
        Cloud(points[:3], colors[:2])


def test_without_open3d_the_global_step_names_the_extra_and_the_local_step_runs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # (an import of it now fails)
    points, colors = room()
    T = small_transform()
    everything = np.ones(len(points), bool)
    source, target = agents(
        points, colors, T, source_part=everything, target_part=everything, noise=0.003
    )
    with pytest.raises(MissingDependencyError, match=r"global step.*gscompress\[align\]"):
        align_clouds(source, target)
    for local in (
        refine_alignment(source, target, np.eye(4)),
        align_clouds(source, target, init=np.eye(4)),
    ):
        dt, dr = transform_error(local.T_target_source, T)
        assert dt < 0.002 and dr < 0.1, (dt, dr)
        assert local.icp == "builtin" and local.refused == ""
    with pytest.raises(MissingDependencyError, match=r"icp 'open3d'.*gscompress\[align\]"):
        refine_alignment(source, target, np.eye(4), AlignOptions(icp="open3d"))


def small_transform() -> np.ndarray:
    """2 cm and 1 degree: what separates two agents' maps anchored in one frame."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(1.0) * np.array([0.6, -0.8, 0.0])).as_matrix()
    T[:3, 3] = [0.012, -0.01, 0.012]
    return T


@pytest.mark.parametrize(
    "icp", [p if p != "open3d" else pytest.param(p, marks=needs_open3d) for p in ICP]
)
def test_the_local_step_recovers_a_known_small_transform(icp: str) -> None:
    points, colors = room()
    T = small_transform()
    everything = np.ones(len(points), bool)
    source, target = agents(
        points, colors, T, source_part=everything, target_part=everything, noise=0.003
    )
    result = refine_alignment(source, target, np.eye(4), AlignOptions(icp=icp))
    dt, dr = transform_error(result.T_target_source, T)
    assert dt < 0.002 and dr < 0.1, (dt, dr)  # (from 2 cm and 1 degree off)
    assert result.icp == icp and result.overlap > 0.9


@needs_open3d
def test_the_builtin_grid_and_icp_are_open3ds() -> None:
    """`grid_cloud` is Open3D's voxel grid with its normals, and the builtin coloured and
    point-to-plane ICP land where Open3D's do, from the same grids."""
    import open3d as o3d

    points, colors = room(0.02)
    T = small_transform()
    everything = np.ones(len(points), bool)
    source, target = agents(
        points, colors, T, source_part=everything, target_part=everything, noise=0.003
    )
    voxel = 0.03
    grid = grid_cloud(target, voxel)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target.points))
    pcd.colors = o3d.utility.Vector3dVector(target.colors)
    theirs = pcd.voxel_down_sample(voxel)
    theirs.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    ours, order = np.lexsort(grid.points.T), np.lexsort(np.asarray(theirs.points).T)
    np.testing.assert_array_equal(grid.points[ours], np.asarray(theirs.points)[order])
    np.testing.assert_array_equal(grid.colors[ours], np.asarray(theirs.colors)[order])
    assert grid.normals is not None
    cosine = np.einsum("ij,ij->i", grid.normals[ours], np.asarray(theirs.normals)[order])
    assert np.abs(cosine).min() > 1.0 - 1e-9  # (Open3D's turn them otherwise)
    src, tgt = grid_cloud(source, voxel), grid
    for colored in (True, False):
        ours_T = ICP["builtin"](src, tgt, np.eye(4), 2 * voxel, FINE_STAGES, colored)
        open3d_T = ICP["open3d"](src, tgt, np.eye(4), 2 * voxel, FINE_STAGES, colored)
        assert transform_error(ours_T, T)[0] < 0.002
        np.testing.assert_allclose(ours_T, open3d_T, atol=1e-6)


def test_map_cloud_keeps_opaque_gaussians_and_flat_normals() -> None:
    means = np.zeros((3, 3))
    scales = np.array([[0.1, 0.1, 0.001], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1]])
    R = np.stack([Rotation.from_rotvec([np.pi / 2, 0, 0]).as_matrix(), np.eye(3), np.eye(3)])
    cloud = map_cloud(means, np.full((3, 3), 0.5), np.array([0.9, 0.9, 0.1]), scales, R)
    assert len(cloud.points) == 2 and cloud.normals is not None
    np.testing.assert_allclose(np.abs(cloud.normals[0]), [0, 1, 0], atol=1e-12)  # z turned to y
    assert not cloud.normals[1].any()  # round: no normal


# ---------------------------------------------------------------- the command


def _write_log(
    path: Path,
    points: np.ndarray,
    colors: np.ndarray,
    views: np.ndarray,
    world: str,
    gt_first: np.ndarray | None = None,
) -> None:
    n = len(points)
    gaussians = GaussianMap.new(
        means=points.astype(np.float32),
        log_scales=np.full((n, 1), np.log(SPACING / 2), np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        opacity_logits=np.full(n, 3.0, np.float32),
        sh_dc=((colors - 0.5) / 0.28209479177387814).astype(np.float32),
    )
    with LogWriter(path, LogMetadata(sequence="room", world_frame=world)) as out:
        for i, c in enumerate(views):
            pose = np.eye(4)
            pose[:3, 3] = c
            out.write_pose(pose, i)
            if gt_first is not None:  # (only the first ground-truth pose matters here)
                out.write_pose(gt_first, i, ground_truth=True)
        out.write_gaussians(gaussians, len(views))


@pytest.fixture
def logs(tmp_path: Path) -> tuple[Path, Path, np.ndarray]:
    points, colors = room()
    T = random_transform(13)
    src_mask, tgt_mask = points[:, 0] < 1.7, points[:, 0] > 0.7
    source, target = tmp_path / "a.mcap", tmp_path / "b.mcap"
    inv = np.linalg.inv(T)
    _write_log(
        source,
        transform_points(inv, points[src_mask]),
        colors[src_mask],
        transform_points(inv, VIEWS),
        "first-camera:room:0",
        gt_first=T,
    )
    _write_log(
        target,
        points[tgt_mask],
        colors[tgt_mask],
        VIEWS,
        "first-camera:room:20",
        gt_first=np.eye(4),
    )
    return source, target, T


@needs_open3d
def test_gsc_align_writes_what_merge_reads(
    logs: tuple[Path, Path, np.ndarray], tmp_path: Path
) -> None:
    source, target, T = logs
    out = tmp_path / "T.txt"
    r = CliRunner().invoke(cli, ["align", str(source), str(target), "-o", str(out), "--json"])
    assert r.exit_code == 0, r.output
    written = read_transform(out)
    dt, dr = transform_error(written, T)
    assert dt < 0.01 and dr < 0.5
    assert "first-camera:room:0" in out.read_text()  # (what it maps, in its comments)
    again = tmp_path / "T2.txt"
    r = CliRunner().invoke(
        cli, ["align", str(source), str(target), "--init", str(out), "-o", str(again), "--json"]
    )
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["global_step"] == "init"
    assert transform_error(read_transform(again), T)[0] < 0.01
    merged = tmp_path / "m.mcap"
    r = CliRunner().invoke(
        cli,
        [
            "merge",
            str(target),
            str(source),
            "--iters",
            "0",
            "--no-align",
            "--resolve",
            "stack",  # the exact concatenation
            "--share-transform",
            str(out),
            "-o",
            str(merged),
        ],
    )
    assert r.exit_code == 0, r.output
    with LogReader(merged) as log, LogReader(target) as b:
        tail = log.read_map().means[len(b.read_map()) :]
    with LogReader(source) as a:
        expected = transform_points(written, a.read_map().means.astype(np.float64))
    np.testing.assert_allclose(tail, expected, atol=1e-5)


def test_gsc_align_without_open3d_refines_a_guess_and_names_the_extra_for_a_search(
    logs: tuple[Path, Path, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # (an import of it now fails)
    source, target, T = logs
    out, guess = tmp_path / "T.txt", tmp_path / "guess.txt"
    r = CliRunner().invoke(cli, ["align", str(source), str(target), "-o", str(out)])
    assert r.exit_code == 1 and not out.exists()
    assert len(r.output.strip().splitlines()) == 1
    assert "global step" in r.output and "pip install 'gscompress[align]'" in r.output
    np.savetxt(guess, small_transform() @ T)
    r = CliRunner().invoke(
        cli, ["align", str(source), str(target), "--init", str(guess), "-o", str(out), "--json"]
    )
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["icp"] == "builtin"
    dt, dr = transform_error(read_transform(out), T)
    assert dt < 0.002 and dr < 0.1, (dt, dr)


@needs_open3d
def test_gsc_align_refuses_in_one_line_without_output(tmp_path: Path) -> None:
    points, colors = _symmetric_room()
    a, b, out = tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "T.txt"
    _write_log(a, transform_points(random_transform(4), points), colors, VIEWS, "first-camera:x:0")
    _write_log(b, points, colors, VIEWS, "first-camera:x:9")
    r = CliRunner().invoke(cli, ["align", str(a), str(b), "-o", str(out)])
    assert r.exit_code == 1 and not out.exists()
    assert r.output.startswith("Error: align a.mcap to b.mcap: ")
    assert len(r.output.strip().splitlines()) == 1


@needs_open3d
def test_share_align_to_cuts_a_share_in_the_targets_frame(
    logs: tuple[Path, Path, np.ndarray], tmp_path: Path
) -> None:
    source, target, T = logs
    share = tmp_path / "s.mcap"
    r = CliRunner().invoke(
        cli,
        [
            "share",
            str(source),
            str(share),
            "--budget",
            "0.5",
            "--codec",
            "fp32",
            "--by",
            "opacity",
            "--no-fold",
            "--align-to",
            str(target),
        ],
    )
    assert r.exit_code == 0, r.output
    with LogReader(share) as s, LogReader(source) as a:
        shared, meta = s.read_map(), s.metadata
        full = a.read_map()
    assert meta.world_frame == "first-camera:room:20"  # the target's: merge takes it as is
    assert meta.provenance[-1]["operation"]["align_to"]["target"] == "b.mcap"
    original = full.means[np.searchsorted(full.ids, shared.ids)].astype(np.float64)
    moved = transform_points(T, original)
    assert np.max(np.linalg.norm(shared.means - moved, axis=1)) < 0.02
    merged = tmp_path / "m.mcap"
    r = CliRunner().invoke(
        cli, ["merge", str(target), str(share), "--iters", "0", "-o", str(merged)]
    )
    assert r.exit_code == 0, r.output


@needs_open3d
def test_gsc_align_does_not_import_torch(
    logs: tuple[Path, Path, np.ndarray], tmp_path: Path
) -> None:
    source, target, _ = logs
    code = (
        "import sys\nfrom gscompress_cli.main import cli\n"
        "try:\n    cli(sys.argv[1:])\nexcept SystemExit as e:\n    assert e.code == 0, e\n"
        "print('torch' in sys.modules)\n"
    )
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "align",
            str(source),
            str(target),
            "-o",
            str(tmp_path / "T.txt"),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert out.stdout.strip().splitlines()[-1] == "False"


@needs_open3d
def test_align_agents_scores_the_estimate_against_the_first_poses(
    logs: tuple[Path, Path, np.ndarray], tmp_path: Path
) -> None:
    from gscompress.pipeline.align import align_agents

    source, target, T = logs
    est, true = tmp_path / "est.txt", tmp_path / "true.txt"
    record = align_agents(source, target, est, true)
    np.testing.assert_allclose(read_transform(true), T, atol=1e-9)  # A's first pose, B's at I
    assert record["refused"] == "" and record["error_cm"] < 1.0 and record["error_deg"] < 0.5
    assert record["drift_cm"] < 1.0  # (the maps were cut from one scene: nothing to drift)
    assert transform_error(read_transform(est), T)[0] * 100 == pytest.approx(record["error_cm"])
    far = tmp_path / "far.mcap"  # a map that shares too little with the target
    points, colors = room()
    mask = points[:, 0] < 0.5
    _write_log(far, points[mask], colors[mask], VIEWS, "first-camera:room:0", np.eye(4))
    record = align_agents(far, target, est, true)
    assert record["refused"].startswith("align far.mcap to b.mcap: ")  # (whatever the reason)
    assert est.exists()  # (the untrusted estimate, for what is counted a miss)


@needs_open3d
@pytest.mark.parametrize("loss, accepted", [(1.5, True), (2.5, False), (None, False)])
def test_the_frames_judge_a_registration_only_its_feature_matches_fault(
    logs: tuple[Path, Path, np.ndarray],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    loss: float | None,
    accepted: bool,
) -> None:
    """With the target's frames, a registration refused for too few agreeing feature matches
    stands when, refined on the frames, the source draws them at most twice as badly as the
    target's own map; a registration refused for anything else is refused as before."""
    import gscompress.pipeline.aligning as aligning

    source, target, T = logs
    found = align_clouds(*(aligning.log_cloud(p)[0] for p in (source, target)))
    few = AlignOptions(min_inliers=10**6)  # (so that the feature matches alone refuse it)
    refined = T.copy()  # (what the frames make of it, stood in for: 3 mm off)
    refined[:3, 3] += [0.003, 0.0, 0.0]

    def on_frames(*args: object) -> tuple[np.ndarray, dict]:
        return refined, {
            "views": 3,
            "loss": loss,
            "target_loss": 1.0,
            "change_cm": 0.0,
            "change_deg": 0.0,
            "seq": "seq",
        }

    monkeypatch.setattr(aligning, "refined_on_frames", on_frames)
    seq = tmp_path  # (any folder: the frames are stood in for above)
    if accepted:
        T_out, record = aligning.align_logs_transform(source, target, options=few, seq=seq)
        assert (
            record["refused"] == ""
            and "too few feature matches" in record["on_frames"]["overruled"]
        )
        assert record["on_frames"]["surface_kept"] >= 0.8
        np.testing.assert_allclose(T_out, refined)
    else:
        with pytest.raises(AlignmentError, match=r"too few feature matches agree.*; .*frames"):
            aligning.align_logs_transform(source, target, options=few, seq=seq)
    with pytest.raises(AlignmentError, match="too few feature matches"):  # (no frames: refused)
        aligning.align_logs_transform(source, target, options=few)
    little = AlignOptions(min_overlap=0.99, min_inliers=10**6)  # (another fault: refused)
    with pytest.raises(AlignmentError, match="too little overlap"):
        aligning.align_logs_transform(source, target, options=little, seq=seq)
    assert found.refused == ""  # (with the default thresholds the registration stands)


@needs_open3d
def test_frames_that_pull_the_source_off_the_surfaces_are_not_taken(
    logs: tuple[Path, Path, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A refinement that leaves less than `SURFACE_KEPT` of the registration's overlap keeps the
    registration's transform, and cannot vouch for a registration refused alone."""
    import gscompress.pipeline.aligning as aligning
    from gscompress.pipeline.align import write_transform_file

    source, target, T = logs
    off = T.copy()
    off[:3, 3] += [0.1, 0.1, 0.1]  # (17 cm across every wall: off the room's surfaces)

    def on_frames(*args: object) -> tuple[np.ndarray, dict]:
        return off, {
            "views": 3,
            "loss": 0.5,
            "target_loss": 1.0,
            "change_cm": 17.3,
            "change_deg": 0.0,
            "seq": "seq",
        }

    monkeypatch.setattr(aligning, "refined_on_frames", on_frames)
    T_out, record = aligning.align_logs_transform(source, target, seq=tmp_path)
    assert record["on_frames"]["kept_registration"] and record["on_frames"]["surface_kept"] < 0.8
    assert transform_error(T_out, T)[0] < 0.01  # (the registration's)
    out = tmp_path / "T.txt"
    write_transform_file(out, T_out, record)
    assert "kept the registration" in out.read_text()
    few = AlignOptions(min_inliers=10**6)
    with pytest.raises(AlignmentError, match="leaves its surfaces"):
        aligning.align_logs_transform(source, target, options=few, seq=tmp_path)
