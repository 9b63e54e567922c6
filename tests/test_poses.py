"""Keyframe poses refined with the map (`PoseConfig`), and the refined trajectory in the log."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gscompress.camera import invert_transform, make_transform, quat_to_rotmat
from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.io.mcap_log import (
    TOPIC_POSE,
    TOPIC_POSE_REFINED,
    LogMetadata,
    LogReader,
    LogWriter,
    decode_trajectory,
)
from gscompress.pipeline import resume_slam_file, slam_file
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.slam.config import preset
from gscompress.slam.keyframes import View
from gscompress.slam.system import SlamSystem

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

SIZE = (64, 48)


def pose_error(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """(translation error in cm, rotation error in degrees)."""
    d = invert_transform(T_ref) @ T
    angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
    return 100 * float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3])), float(angle)


def nudge(T: np.ndarray, degrees: float, offset: list[float]) -> np.ndarray:
    """T moved by a rotation of `degrees` about a fixed axis and a camera-frame offset (m)."""
    axis = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])
    half = np.deg2rad(degrees) / 2
    R = quat_to_rotmat(np.array([np.cos(half), *(np.sin(half) * axis)]))
    return T @ make_transform(R, offset)


def test_the_joint_refinement_recovers_a_keyframe_pose_perturbation():
    # A map made at the true poses of five frames; one keyframe is then put 1.5 cm and 1 degree
    # off. The other views hold the map in place, so refining the map and the open pose
    # together must bring that keyframe back (its pose is the only thing that moves it there).
    seq = synthetic_sequence(5, SIZE)
    config = preset("tiny").with_overrides(**{"tracking.use_ground_truth": True})
    system = SlamSystem(config, seq.intrinsics, total_frames=None)
    for i in range(len(seq)):
        system.process(seq.frame(i))
    truth = seq.frame(2).T_world_cam
    off = nudge(truth, 1.0, [0.010, -0.008, 0.008])
    views = [View.from_frame(i, seq.frame(i), seq.frame(i).T_world_cam, "cpu") for i in range(5)]
    views[2] = View.from_frame(2, seq.frame(2), off, "cpu").refinable(np.repeat([2e-3, 2e-3], 3))
    before = pose_error(views[2].T_world_cam, truth)
    stats = system.mapper.refine(views, 300, np.random.default_rng(0), poses=True)
    after = pose_error(views[2].T_world_cam, truth)
    assert stats.iters == 300 and views[2].refined
    assert after[0] < before[0] / 3 and after[1] < before[1] / 3, (before, after)
    for fixed in (0, 1, 3, 4):  # views without an open pose keep theirs exactly
        np.testing.assert_array_equal(views[fixed].T_world_cam, seq.frame(fixed).T_world_cam)


def test_without_pose_refinement_the_refined_trajectory_is_the_tracked_one():
    seq = synthetic_sequence(4, SIZE)
    system = SlamSystem(preset("tiny"), seq.intrinsics, total_frames=4)
    for i in range(4):
        system.process(seq.frame(i))
    for refined, tracked in zip(system.refined_poses(), system.poses, strict=True):
        np.testing.assert_array_equal(refined, tracked)


def test_a_frame_without_a_refined_view_moves_with_its_keyframe():
    # keyframes every 2nd frame, window refinement only: frame 3 is no keyframe and keeps its
    # tracked pose relative to keyframe 2, whatever the mapping did to keyframe 2's pose
    seq = synthetic_sequence(4, SIZE)
    overrides = {"poses.window": True, "keyframes.every": 2, "mapping.iters": 30}
    config = preset("tiny").with_overrides(**overrides)
    system = SlamSystem(config, seq.intrinsics, total_frames=4)
    for i in range(4):
        system.process(seq.frame(i))
    refined = system.refined_poses()
    keyframe = next(v for v in system.keyframes if v.index == 2)
    assert keyframe.refined  # frame 3's window stepped it
    relative = invert_transform(system.poses[2]) @ system.poses[3]
    np.testing.assert_allclose(invert_transform(refined[2]) @ refined[3], relative, atol=1e-9)
    np.testing.assert_array_equal(refined[0], system.poses[0])  # the anchor never moves
    assert pose_error(refined[2], system.poses[2])[0] > 0


def test_the_refined_trajectory_round_trips_through_a_log(tmp_path: Path):
    rng = np.random.default_rng(3)
    poses = [nudge(np.eye(4), float(a), list(rng.normal(0, 0.1, 3))) for a in (0, 3, 7, 11)]
    path = tmp_path / "t.mcap"
    with LogWriter(path, LogMetadata()) as out:
        for k, T in enumerate(poses):
            out.write_pose(T, 10 * k)
        out.write_trajectory(np.array(poses[:2]) + 0.0, 10)  # an earlier, shorter one
        moved = [T @ make_transform(np.eye(3), [0.01, 0, 0]) for T in poses[:3]]
        out.write_trajectory(np.array(moved), 20)
    with LogReader(path) as log:
        found = log.read_trajectory()
        _, tracked = log.read_poses(TOPIC_POSE)
    assert found.refined == 3 and found.source == "refined, then tracked"
    np.testing.assert_allclose(found.T_world_cam[:3], moved, atol=1e-12)
    np.testing.assert_allclose(found.T_world_cam[3], tracked[3], atol=0)
    np.testing.assert_array_equal(found.times_ns, [0, 10, 20, 30])


def test_a_log_without_a_refined_trajectory_gives_its_tracked_poses(tmp_path: Path):
    path = tmp_path / "t.mcap"
    with LogWriter(path, LogMetadata()) as out:
        out.write_pose(np.eye(4), 0)
    with LogReader(path) as log:
        found = log.read_trajectory()
    assert found.refined == 0 and found.source == "tracked" and len(found.T_world_cam) == 1


def test_a_refined_trajectory_longer_than_the_poses_is_refused(tmp_path: Path):
    from gscompress.errors import LogFormatError

    path = tmp_path / "t.mcap"
    with LogWriter(path, LogMetadata()) as out:
        out.write_pose(np.eye(4), 0)
        out.write_trajectory(np.array([np.eye(4), np.eye(4)]), 0)
    with LogReader(path) as log, pytest.raises(LogFormatError, match="refined trajectory"):
        log.read_trajectory()


@pytest.fixture(scope="module")
def refining_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "tiny.yaml"
    text = "preset: tiny\ncheckpoint_every: 4\nposes:\n  window: true\n  final: true\n"
    path.write_text(text + "mapping:\n  final_iters: 20\n  iters: 30\n  final_views: frames\n")
    return path


def test_a_run_that_refines_poses_logs_its_refined_trajectory(
    seq_dir: Path, refining_config: Path, tmp_path: Path
):
    out = tmp_path / "a.mcap"
    summary = slam_file(seq_dir, out, SlamOptions(config_path=refining_config))
    with LogReader(out) as log:
        found = log.read_trajectory()
        _, tracked = log.read_poses(TOPIC_POSE)
        refined_messages = sum(c.messages for c in log.channels if c.topic == TOPIC_POSE_REFINED)
        results = log.metadata.results
    assert found.refined == len(tracked) == 6 and refined_messages >= 2  # checkpoints + end
    moved = [pose_error(a, b)[0] for a, b in zip(found.T_world_cam, tracked, strict=True)]
    assert moved[0] == 0 and max(moved) > 0  # the anchor fixed, the others refined
    assert results["ate_rmse_cm"] != results["ate_rmse_cm_tracked"]
    assert summary["frames"] == 6


def test_a_resumed_run_places_its_views_at_the_refined_poses_it_logged(
    seq_dir: Path, refining_config: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    # stopped after 5 frames: the log closes with the map and the trajectory as refined then
    # (keyframe 2 moved by the windows of frames 3 and 4); the resume must restore its views
    # there, not at the tracked poses
    out = tmp_path / "a.mcap"

    def stop(done: int, total: int, stats: dict) -> None:
        if done == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        slam_file(seq_dir, out, SlamOptions(config_path=refining_config), progress=stop)
    with LogReader(out) as log:
        logs = [decode_trajectory(s, m) for s, _, m in log.iter_messages([TOPIC_POSE_REFINED])]
        _, tracked = log.read_poses(TOPIC_POSE)
    assert [len(t) for t in logs] == [2, 4, 5]  # a pruning stage, the checkpoint, the stop
    logged = logs[-1]
    assert pose_error(logged[2], tracked[2])[0] > 0  # keyframe 2 was refined
    restored: list[dict[int, np.ndarray]] = []
    original = SlamSystem.restore

    def spy(self: SlamSystem, *args: object, **kwargs: object) -> None:
        original(self, *args, **kwargs)  # type: ignore[arg-type]
        restored.append({v.index: v.T_world_cam.copy() for v in self.views})

    monkeypatch.setattr(SlamSystem, "restore", spy)
    resume_slam_file(seq_dir, out)
    (views,) = restored
    assert sorted(views) == [0, 1, 2, 3, 4]
    for position in range(5):
        np.testing.assert_allclose(views[position], logged[position], atol=1e-12)
    with LogReader(out) as log:
        assert log.read_trajectory().refined == 6
