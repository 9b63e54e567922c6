"""A lost track (`gscompress.slam.lost`): detected from the depth error's running level, a gap
in the stamps or a frame off the map; re-localised against the map, else the run stops in one
line with a valid log of the frames before it."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from gscompress.camera import invert_transform, make_transform, quat_to_rotmat
from gscompress.datasets.base import Frame
from gscompress.datasets.synthetic import synthetic_sequence, write_synthetic_sequence
from gscompress.errors import TrackingLostError
from gscompress.io.mcap_log import LogReader
from gscompress.slam.config import TrackingConfig, preset
from gscompress.slam.lost import TrackLevel, gap_reason, lost_reason, relocalisation_guesses
from gscompress.slam.system import SlamSystem
from gscompress.slam.tracker import TrackResult, constant_velocity, velocity_guess
from tests.conftest import gsc

SIZE = (64, 48)
FIRST = 8  # frames 0..7 are mapped, then frames go missing:
JUMP_TO = 23  # all up to the room's last (of 24) without a gap in the stamps,
GAP_TO = 12  # four, which the stamps show


def result(depth: float, pixels: int = 900) -> TrackResult:
    return TrackResult(np.eye(4), 0.1, 0.1, 40, pixels, 0.05, depth)


def motion(degrees: float, offset: list[float]) -> np.ndarray:
    axis = np.array([0.2, 0.9, -0.3]) / np.linalg.norm([0.2, 0.9, -0.3])
    half = np.deg2rad(degrees) / 2
    return make_transform(quat_to_rotmat(np.array([np.cos(half), *(np.sin(half) * axis)])), offset)


def test_the_level_is_the_median_of_the_latest_accepted_frames():
    level = TrackLevel()
    for depth in (0.01, 0.02):
        level.add(result(depth))
    assert level.level() is None  # too few to judge by
    level.add(result(float("nan")))  # (a frame without pixels counts for nothing)
    assert level.level() is None
    for depth in (0.03, 0.5, 0.04, *[0.01] * 7):
        level.add(result(depth))
    assert level.level() == pytest.approx(0.01)  # only the last 10, and the outlier is outvoted


def test_lost_on_a_depth_error_far_above_its_level_or_too_little_of_the_frame_on_the_map():
    config = TrackingConfig()
    assert lost_reason(result(0.029), 1000, 0.01, config) is None
    assert "3.1x the running level" in str(lost_reason(result(0.031), 1000, 0.01, config))
    assert lost_reason(result(float("nan")), 1000, 0.01, config) is not None
    assert "1% of its depth" in str(lost_reason(result(0.01, pixels=10), 1000, 0.01, config))
    assert lost_reason(result(0.01, pixels=0), 0, 0.01, config) is not None
    # a run's first frames (or a resumed run's) are not judged: there is no level yet
    assert lost_reason(result(0.5, pixels=0), 1000, None, config) is None
    never = dataclasses.replace(config, lost_factor=0.0, lost_coverage=0.0)
    assert lost_reason(result(9.0, pixels=1), 1000, 0.01, never) is None


def test_a_gap_longer_than_max_gap_is_a_lost_track():
    config = TrackingConfig(max_gap=0.5)
    assert gap_reason(0.5, config) is None
    assert "0.600 s after the previous frame" in str(gap_reason(0.6, config))
    assert gap_reason(60.0, dataclasses.replace(config, max_gap=0.0)) is None


def test_the_velocity_guess_spans_the_stamps_interval():
    step = motion(2.0, [0.03, -0.01, 0.02])
    T2 = make_transform(quat_to_rotmat(np.array([0.9, 0.1, -0.3, 0.2]) / 1.0), [1.0, 2.0, 0.5])
    T2 = constant_velocity(T2, None)  # (orthonormal)
    T1 = T2 @ step
    # intervals that differ by jitter only repeat the last motion exactly
    assert np.array_equal(velocity_guess(T1, T2, 0.033, 0.040), constant_velocity(T1, T2))
    # two frames dropped: the motion of three intervals; the frame after a gap: a third of it
    three = velocity_guess(T1, T2, 0.033, 0.099)
    np.testing.assert_allclose(three, T1 @ step @ step @ step, atol=1e-9)
    third = velocity_guess(T1, T2, 0.099, 0.033)
    np.testing.assert_allclose(third, T1 @ _cube_root(step), atol=1e-9)
    np.testing.assert_allclose(
        _cube_root(step) @ _cube_root(step) @ _cube_root(step), step, atol=1e-9
    )


def _cube_root(T: np.ndarray) -> np.ndarray:
    from scipy.linalg import expm, logm

    return np.real(expm(logm(T) / 3))


def test_the_relocalisation_guesses():
    previous, velocity = motion(1.0, [0.01, 0.0, 0.0]), motion(2.0, [0.02, 0.0, 0.0])
    keyframes = [motion(5.0 * k, [0.1 * k, 0.0, 0.0]) for k in range(5)]
    first = ("the velocity guess", velocity)
    names = [name for name, _ in relocalisation_guesses(first, previous, keyframes)]
    assert names == [
        "the velocity guess",
        "the previous pose",
        *(f"keyframe pose {k} back" for k in (1, 2, 3)),
    ]
    guesses = dict(relocalisation_guesses(first, previous, keyframes))
    np.testing.assert_allclose(guesses["keyframe pose 1 back"], keyframes[-1], atol=1e-12)
    # a frame whose own guess is the previous pose does not try it twice
    own = relocalisation_guesses(("the previous pose", previous), previous, keyframes)
    assert [name for name, _ in own].count("the previous pose") == 1


# ---------------------------------------------------------------------------- whole runs


def mapped(config_overrides: dict | None = None) -> tuple[SlamSystem, list[Frame]]:
    """A system (cpu preset) that has tracked and mapped the room's first FIRST frames (of 24),
    and the room's frames."""
    seq = synthetic_sequence(24, SIZE)
    config = preset("cpu").with_overrides(**(config_overrides or {}))
    system = SlamSystem(config, seq.intrinsics, total_frames=None)
    frames = [seq.frame(i) for i in range(len(seq))]
    for frame in frames[:FIRST]:
        system.process(frame)
    return system, frames


def motion_error(system: SlamSystem, frames: list[Frame], to: int) -> tuple[float, float]:
    """(error, length) in cm of the estimated motion from frame FIRST - 1 to frame `to` (the
    frame just processed): the tiny maps drift, so the jump is judged on its own."""
    truth = frames[FIRST - 1].T_world_cam, frames[to].T_world_cam
    assert truth[0] is not None and truth[1] is not None
    step = invert_transform(truth[0]) @ truth[1]
    estimate = invert_transform(system.poses[-2]) @ system.poses[-1]
    error = np.linalg.norm(estimate[:3, 3] - step[:3, 3])
    return 100 * float(error), 100 * float(np.linalg.norm(step[:3, 3]))


@pytest.mark.slow
def test_frames_missing_without_a_gap_in_the_stamps_stop_the_run():
    # The frames after FIRST - 1 went missing, and the stamps do not show it (a recording that
    # restamped its frames): the velocity guess is JUMP_TO - FIRST + 1 steps short, tracking
    # cannot cover that, and no guess recovers it. The system raises before it changes anything.
    system, frames = mapped()
    gaussians = len(system)
    moved = dataclasses.replace(frames[JUMP_TO], timestamp=frames[FIRST].timestamp)
    with pytest.raises(TrackingLostError) as lost:
        system.process(moved)
    assert str(lost.value).startswith(f"tracking lost at frame {JUMP_TO} (stamp 0.267 s): ")
    assert "the running level" in str(lost.value)
    assert (lost.value.frame, len(system.poses), len(system)) == (JUMP_TO, FIRST, gaussians)


@pytest.mark.slow
def test_missing_frames_that_the_stamps_show_are_tracked_with_the_velocity_over_the_gap():
    system, frames = mapped()
    out = system.process(frames[GAP_TO])
    assert out.tracking is not None and not out.tracking.relocalised
    error, length = motion_error(system, frames, GAP_TO)
    assert error < length / 4, (error, length)
    assert "relocalised" not in out.stats()
    assert math.isfinite(out.stats()["tracking_depth_error"])


@pytest.mark.slow
def test_a_gap_over_max_gap_is_re_localised(caplog):
    gap = (GAP_TO - FIRST + 1) / 30  # seconds between frames FIRST - 1 and GAP_TO
    system, frames = mapped({"tracking.max_gap": gap / 2})
    out = system.process(frames[GAP_TO])
    assert out.tracking is not None and out.tracking.relocalised and out.stats()["relocalised"]
    error, length = motion_error(system, frames, GAP_TO)
    assert error < length / 4, (error, length)
    assert (
        f"frame {GAP_TO} (stamp {frames[GAP_TO].timestamp:.3f} s): tracking lost (it "
        f"comes {gap:.3f} s after the previous frame); re-localised" in caplog.text
    )
    # the next frame, one interval on, is tracked as usual
    after = system.process(frames[GAP_TO + 1])
    assert after.tracking is not None and not after.tracking.relocalised


def write_jump(root: Path) -> Path:
    """The room's first 24 frames at SIZE without frames FIRST..JUMP_TO-1, restamped so that
    the stamps run on evenly."""
    seq = write_synthetic_sequence(root / "jump", 24, SIZE)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        path = seq / name
        lines = path.read_text().splitlines()
        head = [line for line in lines if line.startswith("#")]
        rows = [line.split(" ", 1) for line in lines if not line.startswith("#")]
        kept = [rest for _, rest in rows[:FIRST] + rows[JUMP_TO:]]
        restamped = [f"{stamp} {rest}" for (stamp, _), rest in zip(rows, kept, strict=False)]
        path.write_text("\n".join([*head, *restamped]) + "\n")
    return seq


@pytest.mark.slow
def test_gsc_slam_stops_on_a_lost_track_in_one_line_with_a_log_of_the_frames_before(tmp_path):
    seq = write_jump(tmp_path)
    log = tmp_path / "a.mcap"
    res = gsc("slam", seq, "-o", log, "--preset", "cpu", "--size", "64x48")
    assert res.exit_code == 1, res.output
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1, res.output
    assert errors[0].startswith(
        f"Error: tracking lost at frame {FIRST} (stamp {FIRST / 30:.3f} s): its depth error is "
    ), res.output
    assert errors[0].endswith(
        f"x the running level, and no re-localisation guess recovered it; {log} holds the "
        f"{FIRST} frame(s) before it; to go on, map from there as a second agent (gsc slam SEQ "
        f"--frames {FIRST}: -o next.mcap) and register the two with gsc align next.mcap {log}"
    ), res.output
    with LogReader(log) as reader:
        results = reader.metadata.results
        assert results["frames"] == FIRST and results["interrupted"]
        assert results["lost_at"] == {
            "frame": FIRST,
            "timestamp": pytest.approx(FIRST / 30, abs=1e-6),
        }
        assert len(reader.read_trajectory().T_world_cam) == FIRST


@pytest.mark.slow
def test_a_resumed_run_judges_its_frames_against_the_level_the_interrupted_run_had(
    tmp_path, monkeypatch
):
    from gscompress.pipeline import resume_slam_file, slam_file
    from gscompress.pipeline.slam_run.options import SlamOptions

    seq = write_synthetic_sequence(tmp_path / "room", 8, SIZE)
    levels: dict[str, dict[int, float | None]] = {"whole": {}, "resumed": {}}
    process, name = SlamSystem.process, ["whole"]

    def recorded(self: SlamSystem, frame: Frame):  # type: ignore[no-untyped-def]
        levels[name[0]][len(self.poses)] = self.track_level.level()
        return process(self, frame)

    monkeypatch.setattr(SlamSystem, "process", recorded)
    run = SlamOptions(preset="cpu", size=SIZE)
    slam_file(seq, tmp_path / "whole.mcap", run)

    def stop_after_six(done, total, stats):  # type: ignore[no-untyped-def]
        if done == 6:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        slam_file(seq, tmp_path / "cut.mcap", run, progress=stop_after_six)
    name[0] = "resumed"
    resume_slam_file(seq, tmp_path / "cut.mcap")
    first = min(levels["resumed"])
    assert first == 6 and levels["whole"][6] is not None
    assert levels["resumed"][6] == levels["whole"][6]
