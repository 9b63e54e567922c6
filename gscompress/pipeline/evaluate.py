"""`gsc eval`: a log's final map and trajectory scored against its sequence (needs torch).

The log's estimated poses (`/camera/pose`) are matched to the sequence's frames by time: a
frame matches the pose whose log time is nearest to the frame's timestamp in nanoseconds, when
they differ by at most `POSE_MATCH_TOLERANCE_NS` (1 ms; `gsc slam` writes the frame timestamp
itself, so its logs match exactly, and frames of a 30 Hz camera are 33 ms apart). Frames with no
estimated pose are skipped and counted.

Other poses may stand in for the log's own: another log's estimated poses (`poses_from`, matched
the same way) or a TUM trajectory (`poses`, matched within `TUM_MATCH_TOLERANCE_NS`, 20 ms, the
TUM association's default, as its times come from another clock). `pose_source` reads either, and
`frames_with_poses` is the one lookup of a pose per frame (`gsc score` and `gsc merge` use it too).
With `refine_poses` N > 0 each rendered frame's pose is then also refined against the fixed map
(`gscompress.ops.evaluate.refine_poses`: N iterations of the SLAM tracker, the log's tracking
settings, else those of the default preset) and the images are scored again at the refined poses:
the figures at given poses mix the map with the offset between trajectories, those at refined
poses judge the map.

- Trajectory: `ate_rmse_cm` (evo's `evo_ape tum GT EST -a` RMSE, camera centres, SE(3) without
  scale) and `ate_splatam_cm` (the mean SplaTAM prints, each trajectory first expressed relative
  to its own first pose, as SplaTAM's start at identity) over every matched frame that has a
  ground-truth pose: the sequence's, or `/camera/pose_gt` of the log when the sequence has none.
- Images: the final map (last `/gaussians` snapshot) rendered at the estimated pose of every
  `every`-th matched frame and scored by `gscompress.ops.evaluate.evaluate_map`.
- Refined (with `refine_poses`): the image metrics at the refined poses, and the median change of
  pose (camera centre in cm, rotation in degrees) from the given poses.
- Size: Gaussian count, the serialized `/gaussians` message in bytes (as `gsc info` reports it,
  what would be sent) and the file's bytes.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from gscompress.camera import invert_transform
from gscompress.errors import InputError, LogFormatError, OptionError
from gscompress.io.mcap_log import (
    POSES_GROUND_TRUTH,
    TOPIC_POSE,
    TOPIC_POSE_GT,
    LogMetadata,
    LogReader,
    seconds_to_ns,
)
from gscompress.io.trajectory import nearest_times, read_tum_trajectory
from gscompress.pipeline import logs

log = logging.getLogger(__name__)

GROUND_TRUTH_POSES = (
    "the log's poses are the sequence's ground truth (a map scored or made at the ground-truth "
    "poses), not estimated: their error against it measures nothing"
)
"""The reason ATE is unavailable for a log posed at the ground truth."""

POSE_MATCH_TOLERANCE_NS = 1_000_000
"""Largest |log time - frame timestamp| (ns) at which a logged pose belongs to a frame."""

TUM_MATCH_TOLERANCE_NS = 20_000_000
"""Largest |trajectory time - frame timestamp| (ns) at which a TUM trajectory's pose belongs to a
frame (0.02 s, the default of TUM's association tool)."""


class Poses(NamedTuple):
    """The poses a file gives (`pose_source`).

    Attributes:
        times_ns: [N] int64 times.
        T_world_cam: [N, 4, 4] camera-to-world poses.
        tolerance_ns: how far a time may be from a frame's timestamp and still be its pose.
        trajectory: "refined" / "tracked" / "refined, then tracked" for a log's, "file" for a
            TUM trajectory's.
    """

    times_ns: np.ndarray
    T_world_cam: np.ndarray
    tolerance_ns: int
    trajectory: str


def pose_source(path: str | Path) -> Poses:
    """The poses a file gives: a log's trajectory (refined where it has one: `logs.trajectory`),
    or a TUM trajectory's.

    Raises:
        LogFormatError: a log without `/camera/pose`, or unreadable.
        InputError: an unreadable or empty trajectory.
    """
    if Path(path).suffix.lower() == ".mcap":
        with LogReader(path) as reader:
            found = logs.trajectory(reader)
        if len(found.times_ns) == 0:
            raise LogFormatError(
                f"{path} has no {TOPIC_POSE} messages (not a SLAM log): no poses to render at; "
                "give them with --poses TRAJ.txt or --poses-from OTHER.mcap"
            )
        return Poses(found.times_ns, found.T_world_cam, POSE_MATCH_TOLERANCE_NS, found.source)
    trajectory = read_tum_trajectory(path)
    if len(trajectory) == 0:
        raise InputError(f"{path} holds no poses")
    times_ns = np.array([seconds_to_ns(t) for t in trajectory.timestamps], dtype=np.int64)
    return Poses(times_ns, trajectory.T_world_cam, TUM_MATCH_TOLERANCE_NS, "file")


def working_size(meta: LogMetadata) -> tuple[int, int] | None:
    """The working size (W, H) a log's run recorded in its config, or None (a share, whose
    config stays with the sender, or a run at the sequence's own size)."""
    recorded = meta.config.get("size")
    return (int(recorded[0]), int(recorded[1])) if recorded else None


def open_log_sequence(
    seq: str | Path,
    log_path: str | Path,
    meta: LogMetadata,
    frames: str | None = None,
    size: tuple[int, int] | None = None,
    recording: Any = None,
) -> Any:
    """The sequence a log was made from, opened as its run had it: the log's frame subset,
    working size and (a recording) topics unless given. Warns when the sequence is not the one
    the log names (its poses would then be compared with frames they do not belong to), and
    when the working size enlarges its frames.

    Raises:
        InputError: opened as the log's run had it, the sequence's first frame is not the one
            the log recorded (another scene under the same name).
    """
    from gscompress.datasets import RecordingOptions, open_sequence
    from gscompress.datasets.base import enlargement_note
    from gscompress.datasets.recording import is_recording

    recorded_size = working_size(meta)
    size = size or recorded_size
    subset = frames or meta.frames or "all"
    if (recording is None or recording.is_default) and is_recording(Path(seq)):
        recorded = RecordingOptions.from_record(meta.results.get("recording"))
        if recorded is not None and recorded.gt is not None and not recorded.gt.is_file():
            log.warning("%s: the run's ground truth %s is gone; using the log's", log_path,
                        recorded.gt)  # fmt: skip
            recorded = replace(recorded, gt=None)
        recording = recorded or recording
    sequence = open_sequence(seq, size=size, frames=subset, recording=recording)
    if meta.sequence and meta.sequence != sequence.name:
        log.warning("%s was recorded from sequence %r, not %r", log_path, meta.sequence,
                    sequence.name)  # fmt: skip
    as_recorded = subset == (meta.frames or "all") and list(size or []) == list(recorded_size or [])
    if as_recorded and len(sequence):  # (the first frame then is the one the run saw)
        check_first_frame(log_path, meta.results.get("first_frame"), sequence)
    if note := enlargement_note(sequence):
        log.warning("%s", note)
    return sequence


def check_first_frame(log_path: str | Path, recorded: Any, sequence: Any) -> list[float]:
    """The fingerprint of the sequence's first frame (`Frame.fingerprint`), checked against the
    one a log recorded of its own first frame (`results.first_frame`; older logs have none).

    Raises:
        InputError: they differ: the sequence is another scene (under the log's sequence name
            or another).
    """
    from gscompress.datasets.base import recorded_fingerprint, same_fingerprint

    found: list[float] = sequence.frame(0).fingerprint()
    recorded = recorded_fingerprint(recorded)
    if recorded is not None and not same_fingerprint(recorded, found):
        raise InputError(
            f"{log_path} was not recorded on this {sequence.name}: its first frame differs "
            f"(mean depth and colour {recorded} against {found})"
        )
    return found


def frames_with_poses(
    sequence: Any,
    pose_ns: np.ndarray,
    log_path: str | Path,
    tolerance_ns: int = POSE_MATCH_TOLERANCE_NS,
) -> tuple[np.ndarray, np.ndarray]:
    """The positions of the sequence's frames that have a pose (times `pose_ns`, from the file
    `log_path`) within `tolerance_ns` of their timestamp, and the index of each one's pose.

    Raises:
        InputError: no frame has one.
    """
    frame_ns = np.array([seconds_to_ns(t) for t in sequence.timestamps], dtype=np.int64)
    index = nearest_times(frame_ns, pose_ns, tolerance_ns)
    positions = np.flatnonzero(index >= 0)
    if len(positions) == 0:
        raise InputError(
            f"no frame of {sequence.name} has a pose in {log_path} within "
            f"{tolerance_ns / 1e6:g} ms: is this the sequence (and frame subset) the poses "
            "were made from?"
        )
    return positions, index[positions]


def carried_times(meta: LogMetadata, reader: LogReader | None = None) -> np.ndarray:
    """[K] int64 timestamps (ns) of the frames a share carried into this map and a merge
    refined it on (`carried_ns` of its provenance's merge steps), and, given the file's
    `reader`, of the keyframes it carries itself (a share's), sorted."""
    times: set[int] = set()
    if reader is not None:
        from gscompress.io.keyframes import TOPIC_KEYFRAME_POSE

        times.update(reader.read_poses(TOPIC_KEYFRAME_POSE)[0].tolist())
    for step in meta.provenance:
        operation = step.get("operation") if isinstance(step, dict) else None
        values = operation.get("carried_ns") if isinstance(operation, dict) else None
        if isinstance(values, list):
            times.update(int(t) for t in values if isinstance(t, int) and not isinstance(t, bool))
    return np.array(sorted(times), dtype=np.int64)


def trajectory_errors(T_world_cam_gt: np.ndarray, T_world_cam_est: np.ndarray) -> dict[str, Any]:
    """Both ATE conventions (cm), or None with the reason when fewer than 2 poses pair up."""
    from gscompress.metrics import ate_rmse_cm, ate_splatam_cm

    n = len(T_world_cam_gt)
    if n < 2:
        reason = f"{n} frame(s) with both an estimated and a ground-truth pose; need 2"
        return {"ate_rmse_cm": None, "ate_splatam_cm": None, "ate_frames": n, "ate_reason": reason}
    gt = invert_transform(T_world_cam_gt[0]) @ T_world_cam_gt
    est = invert_transform(T_world_cam_est[0]) @ T_world_cam_est
    return {
        "ate_rmse_cm": ate_rmse_cm(T_world_cam_gt, T_world_cam_est),
        "ate_splatam_cm": ate_splatam_cm(gt, est),
        "ate_frames": n,
        "ate_reason": "",
    }


def log_tracking_config(meta: LogMetadata) -> Any:
    """The tracking settings of the run a log records (`TrackingConfig`), else those of the
    default preset (a log from another tool, or one whose config this version cannot read)."""
    from gscompress.slam.config import DEFAULT_PRESET, SlamConfig, preset

    if meta.config:
        try:
            return SlamConfig.from_dict(meta.config).tracking
        except InputError as exc:
            log.warning("tracking with the %s preset's settings: %s", DEFAULT_PRESET, exc)
    return preset(DEFAULT_PRESET).tracking


def evaluate_log(
    log_path: str | Path,
    seq: str | Path,
    *,
    frames: str | None = None,
    every: int = 1,
    size: tuple[int, int] | None = None,
    poses: str | Path | None = None,
    poses_from: str | Path | None = None,
    refine_poses: int = 0,
    backend: str = "auto",
    device: str = "auto",
    lpips: bool = True,
    save_images: str | Path | None = None,
    colorings: tuple[str, ...] = ("rgb",),
    side_by_side: bool = True,
    leave_out: Sequence[str | Path] = (),
    progress: Callable[[int, int], object] | None = None,
    recording: Any = None,
) -> dict[str, Any]:
    """Score a log's final map and estimated trajectory against the sequence it was made from.

    Args:
        log_path: a gscompress log with `/gaussians` (and `/camera/pose` unless `poses` or
            `poses_from` gives the poses).
        seq: the sequence folder or recording.
        frames: frame subset; None: the one recorded in the log's metadata (else all).
        every: render every `every`-th frame that has a pose (ATE uses all of them).
        size: working size (W, H); None: the one in the log's config, else (a share) the one
            in `poses_from`'s, else the sequence's own.
        poses: a TUM trajectory to render at instead of the log's poses.
        poses_from: another log whose estimated poses to render at instead.
        refine_poses: also refine each rendered frame's pose against the fixed map with this
            many tracking iterations and score the images again there (0: do not).
        backend: render backend.
        device: torch device to render on, or "auto".
        lpips: compute LPIPS (reported unavailable with the reason when it cannot be).
        save_images: a folder to write pictures of every view scored into
            (`gscompress.pipeline.images.ImageSaver`; those at refined poses in `refined/`).
        colorings: what the pictures are coloured by (`gscompress.pipeline.images.COLORINGS`).
        side_by_side: also write one labelled figure per view (observed, render, error).
        leave_out: other files whose carried keyframes are left out of the scores too
            (`carried_times`): score maps that were not refined on them on the same frames
            as one that was.
        progress: called with (steps done, steps in total) after each view rendered or refined.
        recording: a recording's `RecordingOptions` (None: those the log's run recorded).

    The frames a share carried into this map, which its merge refined on, are never scored
    (`frames_carried_left_out` counts them with those of `leave_out`).

    Returns:
        A flat JSON-ready dict: `poses` (where the poses rendered at came from: the log's
        own, as `LogMetadata.pose_origin` says, "estimated", "ground-truth" or a trajectory
        file; else the --poses or --poses-from file) and `own_poses`, `ate_rmse_cm`,
        `ate_splatam_cm` of those poses (None with `ate_reason` when there is no ground truth,
        or when the log's own poses are the ground truth), `psnr`, `ssim`, `ms_ssim`, `lpips`,
        `depth_l1_cm` at those poses (each None with `<name>_reason` when unavailable),
        `gaussians`, `bytes` (the serialized map message), `file_bytes`, frame counts
        (`frames_selected`, `frames_with_pose`, `frames_without_pose`, `frames_evaluated`), the
        settings used, `per_frame` (per rendered view: index, timestamp and its metrics) and,
        with `refine_poses`, `refined`: the same image metrics at the refined poses, `iters`,
        the median pose change `pose_change_cm` and `pose_change_deg`, and its own `per_frame`
        (with each frame's pose change). With `save_images`, `images` lists the files written.

    Raises:
        LogFormatError: unreadable log, or no `/gaussians`, or no `/camera/pose` where the
            poses come from.
        DatasetError: unreadable sequence.
        InputError: `every` < 1, `refine_poses` < 0, or no frame of the sequence has a pose.
        OptionError: both `poses` and `poses_from`.
    """
    from gscompress.ops.evaluate import EvalView, evaluate_map, pose_change
    from gscompress.ops.evaluate import refine_poses as refine
    from gscompress.pipeline.images import ImageSaver
    from gscompress.render import resolve_device

    if every < 1:
        raise InputError(f"`every` must be a positive integer, got {every}", options=("every",))
    if refine_poses < 0:
        raise InputError(
            f"`refine_poses` must be 0 or more iterations, got {refine_poses}",
            options=("refine_poses",),
        )
    if poses is not None and poses_from is not None:
        raise OptionError(
            "`poses` and `poses_from` do not go together: give one source of poses",
            options=("poses", "poses_from"),
        )
    start = time.perf_counter()
    log_path = Path(log_path)
    with LogReader(log_path) as reader:
        snapshot = reader.read_snapshot()
        gaussians, map_bytes = snapshot.gaussians, snapshot.message_bytes
        gt_log_ns, gt_log_poses = reader.read_poses(TOPIC_POSE_GT)
        meta = reader.metadata
    source = poses if poses is not None else poses_from if poses_from is not None else log_path
    est_ns, est_poses, tolerance_ns, used = pose_source(source)
    frames = frames or meta.frames or "all"
    if size is None and working_size(meta) is None and poses_from is not None:
        with LogReader(poses_from) as other:  # (a share scored at its sender's poses)
            size = working_size(other.metadata)
    sequence = open_log_sequence(seq, log_path, meta, frames, size, recording)
    positions, pose_index = frames_with_poses(sequence, est_ns, source, tolerance_ns)
    T_est = est_poses[pose_index]

    # ground truth per matched frame: the sequence's, else the log's /camera/pose_gt
    gt_stamps, gt_poses = sequence.ground_truth()
    gt_source = "sequence"
    if len(gt_stamps) == 0:
        gt_stamps_ns, gt_poses, gt_source = gt_log_ns, gt_log_poses, "log"
    else:
        gt_stamps_ns = np.array([seconds_to_ns(t) for t in gt_stamps], dtype=np.int64)
        gt_poses = np.asarray(gt_poses)
    frame_ns = np.array([seconds_to_ns(sequence.timestamps[p]) for p in positions], dtype=np.int64)
    gt_index = nearest_times(frame_ns, gt_stamps_ns, POSE_MATCH_TOLERANCE_NS)
    paired = gt_index >= 0
    ate = trajectory_errors(gt_poses[gt_index[paired]], T_est[paired])
    if ate["ate_frames"] == 0 and len(gt_stamps_ns) == 0:
        ate["ate_reason"] = "no ground truth: neither the sequence nor the log has poses"
    ate["ground_truth"] = gt_source if ate["ate_frames"] else None
    own = poses is None and poses_from is None
    if own and meta.pose_origin() == POSES_GROUND_TRUTH:
        ate.update(ate_rmse_cm=None, ate_splatam_cm=None, ate_reason=GROUND_TRUTH_POSES)

    chosen = list(range(0, len(positions), every))
    carried, left_out = carried_times(meta), 0
    for path in leave_out:
        with LogReader(path) as other:
            carried = np.union1d(carried, carried_times(other.metadata, other))
    if len(carried):  # frames a merge refined on: scoring them would flatter the map
        near = nearest_times(frame_ns, carried, POSE_MATCH_TOLERANCE_NS) >= 0
        left_out = int(near[chosen].sum())
        chosen = [k for k in chosen if not near[k]]
        if not chosen:
            raise InputError(
                f"every frame chosen in {sequence.name} was carried into "
                f"{log_path.name} by a share and refined on: none is left to score"
            )
    torch_device = resolve_device(device, backend)

    def views(T_world_cams: Any) -> Iterator[EvalView]:
        for k, T in zip(chosen, T_world_cams, strict=True):
            frame = sequence.frame(int(positions[k]))
            yield EvalView(frame.color, frame.depth, T, frame.index, frame.timestamp)

    total = len(chosen) * (3 if refine_poses else 1)
    done = 0

    def step(n: int) -> None:
        nonlocal done
        done += n
        if progress is not None:
            progress(done, total)

    savers: dict[str, ImageSaver] = {}

    def saver(folder: str) -> ImageSaver | None:
        if save_images is None:
            return None
        savers[folder] = ImageSaver(
            Path(save_images) / folder, gaussians, sequence.intrinsics, colorings,
            side_by_side, backend, torch_device, title=f"{log_path.name} on {sequence.name}",
        )  # fmt: skip
        return savers[folder]

    T_given = [T_est[k] for k in chosen]
    score = partial(
        evaluate_map, gaussians, intrinsics=sequence.intrinsics, backend=backend,
        device=torch_device, lpips=lpips, progress=step,
    )  # fmt: skip
    images = score(views(T_given), on_render=saver(""))
    per_frame = images.pop("per_view")
    refined: dict[str, Any] | None = None
    if refine_poses:
        tracking = replace(log_tracking_config(meta), iters=refine_poses)
        T_refined = refine(
            gaussians, views(T_given), sequence.intrinsics, tracking, backend=backend,
            device=torch_device, progress=step,
        )  # fmt: skip
        refined = score(views(T_refined), on_render=saver("refined"))
        changes = {
            int(sequence.indices[positions[k]]): pose_change(T_given[i], T_refined[i])
            for i, k in enumerate(chosen)
        }
        refined_frames = refined.pop("per_view")
        for record in refined_frames:
            record["pose_change_cm"], record["pose_change_deg"] = changes[record["index"]]
        # (over the frames scored: one without valid depth is neither refined nor scored)
        refined = {
            "iters": refine_poses,
            **median_pose_change(refined_frames),
            **{k: v for k, v in refined.items() if k not in ("views", "views_without_depth")},
            "per_frame": refined_frames,
        }
    intr = sequence.intrinsics
    return {
        "log": str(log_path),
        "sequence": sequence.name,
        "frames": str(frames),
        "size": [intr.width, intr.height],
        "every": every,
        "poses": meta.pose_origin() if own else str(source),
        "own_poses": own,
        "trajectory": used,
        "frames_selected": len(sequence),
        "frames_with_pose": len(positions),
        "frames_without_pose": len(sequence) - len(positions),
        "frames_evaluated": images.pop("views"),
        "frames_carried_left_out": left_out,
        "frames_without_depth": images.pop("views_without_depth"),
        **ate,
        **images,
        "gaussians": len(gaussians),
        "bytes": map_bytes,
        "file_bytes": log_path.stat().st_size,
        "seconds": round(time.perf_counter() - start, 3),
        "per_frame": per_frame,
        **({"refined": refined} if refined is not None else {}),
        **({"images": [str(p) for s in savers.values() for p in s.written]} if savers else {}),
    }


def median_pose_change(per_frame: list[dict[str, Any]]) -> dict[str, float | None]:
    """The median `pose_change_cm` and `pose_change_deg` of the frames whose poses were
    refined (None for none)."""
    moved = np.array([(r["pose_change_cm"], r["pose_change_deg"]) for r in per_frame])
    moved = moved.reshape(-1, 2)
    return {
        "pose_change_cm": float(np.median(moved[:, 0])) if len(moved) else None,
        "pose_change_deg": float(np.median(moved[:, 1])) if len(moved) else None,
    }


def union_results(first: dict[str, Any], second: dict[str, Any]) -> dict[str, Any]:
    """The figures of every frame that either of two `evaluate_log` results of one map scored,
    each frame once: `first`'s where both scored it, so `first` decides where such a frame's
    pose started. Each frame's figures are its own (a pose is refined frame by frame), so the
    union is what one evaluation of those frames from those poses would give, without rendering
    or refining any frame again.

    Returns:
        `frames_evaluated`, the image figures (`METRICS`, their reasons as `first` gives them)
        and `per_frame`, at the starting poses; `refined`, when both refined the poses: the same
        at the refined poses with `iters` and the median pose change.
    """
    from gscompress.ops.evaluate import METRICS, mean_metrics

    def union(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
        seen = {r["index"] for r in a["per_frame"]}
        per_frame = sorted(
            [*a["per_frame"], *(r for r in b["per_frame"] if r["index"] not in seen)],
            key=lambda r: r["index"],
        )  # fmt: skip
        reasons = {m: a.get(f"{m}_reason") or "" for m in METRICS}
        return {**mean_metrics(per_frame, reasons), "per_frame": per_frame}

    result = union(first, second)
    result["frames_evaluated"] = len(result["per_frame"])
    if "refined" in first and "refined" in second:
        refined = union(first["refined"], second["refined"])
        result["refined"] = {
            "iters": first["refined"]["iters"],
            **median_pose_change(refined["per_frame"]),
            **refined,
        }
    return result
