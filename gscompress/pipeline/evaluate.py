"""`gsc eval`: a log's final map and trajectory scored against its sequence (needs torch).

The log's estimated poses (`/camera/pose`) are matched to the sequence's frames by time
(`gscompress.pipeline.logs.frames_with_poses`, within `POSE_MATCH_TOLERANCE_NS`, 1 ms; `gsc
slam` writes the frame timestamp itself, so its logs match exactly, and frames of a 30 Hz camera
are 33 ms apart). Frames with no estimated pose are skipped and counted.

Other poses may stand in for the log's own: another log's estimated poses (`poses_from`, matched
the same way) or a TUM trajectory (`poses`, matched within `TUM_MATCH_TOLERANCE_NS`, 20 ms, the
TUM association's default, as its times come from another clock); `logs.pose_source` reads
either.
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
from gscompress.errors import InputError
from gscompress.io.mcap_log import (
    POSES_GROUND_TRUTH,
    TOPIC_POSE_GT,
    LogMetadata,
    LogReader,
    seconds_to_ns,
)
from gscompress.io.trajectory import nearest_times
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.logs import (
    POSE_MATCH_TOLERANCE_NS,
    carried_times,
    frames_with_poses,
    open_log_sequence,
    pose_source,
    working_size,
)

log = logging.getLogger(__name__)

DEFAULTS = ImageOptions()
"""`gsc eval`'s views and pictures unless asked otherwise."""

GROUND_TRUTH_POSES = (
    "the log's poses are the sequence's ground truth (a map scored or made at the ground-truth "
    "poses), not estimated: their error against it measures nothing"
)
"""The reason ATE is unavailable for a log posed at the ground truth."""


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
    options: ImageOptions = DEFAULTS,
    *,
    refine_poses: int = 0,
    leave_out: Sequence[str | Path] = (),
    progress: Callable[[int, int], object] | None = None,
    recording: Any = None,
) -> dict[str, Any]:
    """Score a log's final map and estimated trajectory against the sequence it was made from.

    Args:
        log_path: a gscompress log with `/gaussians` (and `/camera/pose` unless `poses` or
            `poses_from` gives the poses).
        seq: the sequence folder or recording.
        options: the frames rendered and at which poses, how, and the pictures written of
            them (`ImageOptions`: frames, every, size, poses, poses_from, backend, device,
            lpips, save_images, colorings, side_by_side; those at refined poses in
            `refined/`).
        refine_poses: also refine each rendered frame's pose against the fixed map with this
            many tracking iterations and score the images again there (0: do not).
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
    o = options
    o.check()
    if refine_poses < 0:
        raise InputError(
            f"`refine_poses` must be 0 or more iterations, got {refine_poses}",
            options=("refine_poses",),
        )
    start = time.perf_counter()
    log_path = Path(log_path)
    target = _read_target(log_path)
    meta = target.meta
    own = o.poses is None and o.poses_from is None
    source = log_path if own else o.poses if o.poses is not None else o.poses_from
    assert source is not None
    frames = o.frames or meta.frames or "all"
    matched = _match_frames(seq, log_path, meta, source, frames, o, recording)
    ate = _trajectory_scores(matched, target, own)
    chosen, left_out = _chosen_frames(matched, o.every, meta, leave_out, log_path)
    scored = _image_scores(target, matched, chosen, refine_poses, o, progress, log_path.name)
    pose_text = meta.pose_origin() if own else str(source)
    return _results(
        log_path,
        target,
        matched,
        (frames, o.every, pose_text, own),
        ate,
        left_out,
        scored,
        time.perf_counter() - start,
    )


class _Target(NamedTuple):
    """What `evaluate_log` reads of the log it scores: its final map, the map message's bytes,
    its `/camera/pose_gt` (times and poses) and its metadata."""

    gaussians: Any
    map_bytes: int
    gt_ns: np.ndarray
    gt_poses: np.ndarray
    meta: LogMetadata


def _read_target(log_path: Path) -> _Target:
    """The log's final map with its message's bytes, ground-truth poses and metadata."""
    with LogReader(log_path) as reader:
        snapshot = reader.read_snapshot()
        gaussians, map_bytes = snapshot.gaussians, snapshot.message_bytes
        gt_log_ns, gt_log_poses = reader.read_poses(TOPIC_POSE_GT)
        meta = reader.metadata
    return _Target(gaussians, map_bytes, gt_log_ns, gt_log_poses, meta)


class _Matched(NamedTuple):
    """The frames of a sequence that have a pose where the poses come from.

    Attributes:
        sequence: the sequence, opened as the log's run had it.
        positions: [F] positions in it of the frames with a pose.
        T_est: [F, 4, 4] their poses.
        frame_ns: [F] int64 their timestamps.
        trajectory: which of the file's trajectories the poses are (`Poses.trajectory`).
    """

    sequence: Any
    positions: np.ndarray
    T_est: np.ndarray
    frame_ns: np.ndarray
    trajectory: str


def _match_frames(
    seq: str | Path,
    log_path: Path,
    meta: LogMetadata,
    source: str | Path,
    frames: str,
    options: ImageOptions,
    recording: Any,
) -> _Matched:
    """The log's sequence (`open_log_sequence`: a share scored at its sender's poses, with
    `poses_from`, at the sender's working size unless `size` is given) and its frames that have
    a pose in `source`."""
    est_ns, est_poses, tolerance_ns, used = pose_source(source)
    size, poses_from = options.size, options.poses_from
    if size is None and working_size(meta) is None and poses_from is not None:
        with LogReader(poses_from) as other:  # (a share scored at its sender's poses)
            size = working_size(other.metadata)
    sequence = open_log_sequence(seq, log_path, meta, frames, size, recording)
    positions, pose_index = frames_with_poses(sequence, est_ns, source, tolerance_ns)
    frame_ns = np.array([seconds_to_ns(sequence.timestamps[p]) for p in positions], dtype=np.int64)
    return _Matched(sequence, positions, est_poses[pose_index], frame_ns, used)


def _trajectory_scores(matched: _Matched, target: _Target, own: bool) -> dict[str, Any]:
    """ATE of the matched poses (`trajectory_errors`) over the frames that have a ground-truth
    pose: the sequence's, else the log's `/camera/pose_gt` (`ground_truth` says which); none,
    with the reason, for the log's `own` poses when they are the ground truth."""
    gt_stamps, gt_poses = matched.sequence.ground_truth()
    gt_source = "sequence"
    if len(gt_stamps) == 0:
        gt_stamps_ns, gt_poses, gt_source = target.gt_ns, target.gt_poses, "log"
    else:
        gt_stamps_ns = np.array([seconds_to_ns(t) for t in gt_stamps], dtype=np.int64)
        gt_poses = np.asarray(gt_poses)
    gt_index = nearest_times(matched.frame_ns, gt_stamps_ns, POSE_MATCH_TOLERANCE_NS)
    paired = gt_index >= 0
    ate = trajectory_errors(gt_poses[gt_index[paired]], matched.T_est[paired])
    if ate["ate_frames"] == 0 and len(gt_stamps_ns) == 0:
        ate["ate_reason"] = "no ground truth: neither the sequence nor the log has poses"
    ate["ground_truth"] = gt_source if ate["ate_frames"] else None
    if own and target.meta.pose_origin() == POSES_GROUND_TRUTH:
        ate.update(ate_rmse_cm=None, ate_splatam_cm=None, ate_reason=GROUND_TRUTH_POSES)
    return ate


def _chosen_frames(
    matched: _Matched,
    every: int,
    meta: LogMetadata,
    leave_out: Sequence[str | Path],
    log_path: Path,
) -> tuple[list[int], int]:
    """Every `every`-th matched frame (its index among them) but those a share carried into the
    map or into one of `leave_out` (`carried_times`), and how many of those were left out.

    Raises:
        InputError: every frame chosen was carried.
    """
    chosen = list(range(0, len(matched.positions), every))
    carried, left_out = carried_times(meta), 0
    for path in leave_out:
        with LogReader(path) as other:
            carried = np.union1d(carried, carried_times(other.metadata, other))
    if len(carried):  # frames a merge refined on: scoring them would flatter the map
        near = nearest_times(matched.frame_ns, carried, POSE_MATCH_TOLERANCE_NS) >= 0
        left_out = int(near[chosen].sum())
        chosen = [k for k in chosen if not near[k]]
        if not chosen:
            raise InputError(
                f"every frame chosen in {matched.sequence.name} was carried into "
                f"{log_path.name} by a share and refined on: none is left to score"
            )
    return chosen, left_out


class _Images(NamedTuple):
    """The image scores of `_image_scores`: the metrics with the counts of views
    (`evaluate_map`), `per_frame`, `refined` (None without `refine_poses`) and the pictures
    written (None without `save_images`)."""

    metrics: dict[str, Any]
    per_frame: list[dict[str, Any]]
    refined: dict[str, Any] | None
    written: list[str] | None


def _image_scores(
    target: _Target,
    matched: _Matched,
    chosen: list[int],
    refine_poses: int,
    how: ImageOptions,
    progress: Callable[[int, int], object] | None,
    log_name: str,
) -> _Images:
    """The map rendered at the chosen frames' poses and scored (`evaluate_map`), and, with
    `refine_poses`, scored again at those poses refined against it (`refine_poses`
    iterations of the log's tracking, `log_tracking_config`)."""
    from gscompress.ops.evaluate import EvalView, evaluate_map, pose_change
    from gscompress.ops.evaluate import refine_poses as refine
    from gscompress.pipeline.images import ImageSaver
    from gscompress.render import resolve_device

    gaussians, sequence, positions = target.gaussians, matched.sequence, matched.positions
    backend = how.backend
    torch_device = resolve_device(how.device, backend)

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
        if how.save_images is None:
            return None
        savers[folder] = ImageSaver(
            Path(how.save_images) / folder,
            gaussians,
            sequence.intrinsics,
            how.colorings,
            how.side_by_side,
            backend,
            torch_device,
            title=f"{log_name} on {sequence.name}",
        )
        return savers[folder]

    T_given = [matched.T_est[k] for k in chosen]
    score = partial(
        evaluate_map,
        gaussians,
        intrinsics=sequence.intrinsics,
        backend=backend,
        device=torch_device,
        lpips=how.lpips,
        progress=step,
    )
    images = score(views(T_given), on_render=saver(""))
    per_frame = images.pop("per_view")
    refined: dict[str, Any] | None = None
    if refine_poses:
        tracking = replace(log_tracking_config(target.meta), iters=refine_poses)
        T_refined = refine(
            gaussians,
            views(T_given),
            sequence.intrinsics,
            tracking,
            backend=backend,
            device=torch_device,
            progress=step,
        )
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
    written = [str(p) for s in savers.values() for p in s.written] if savers else None
    return _Images(images, per_frame, refined, written)


def _results(
    log_path: Path,
    target: _Target,
    matched: _Matched,
    settings: tuple[str, int, str, bool],
    ate: dict[str, Any],
    left_out: int,
    scored: _Images,
    seconds: float,
) -> dict[str, Any]:
    """`evaluate_log`'s results (see there); `settings`: the frame subset, `every`, where the
    poses came from and whether they are the log's own."""
    frames, every, pose_text, own = settings
    sequence, positions, images = matched.sequence, matched.positions, scored.metrics
    intr = sequence.intrinsics
    return {
        "log": str(log_path),
        "sequence": sequence.name,
        "frames": str(frames),
        "size": [intr.width, intr.height],
        "every": every,
        "poses": pose_text,
        "own_poses": own,
        "trajectory": matched.trajectory,
        "frames_selected": len(sequence),
        "frames_with_pose": len(positions),
        "frames_without_pose": len(sequence) - len(positions),
        "frames_evaluated": images.pop("views"),
        "frames_carried_left_out": left_out,
        "frames_without_depth": images.pop("views_without_depth"),
        **ate,
        **images,
        "gaussians": len(target.gaussians),
        "bytes": target.map_bytes,
        "file_bytes": log_path.stat().st_size,
        "seconds": round(seconds, 3),
        "per_frame": scored.per_frame,
        **({"refined": scored.refined} if scored.refined is not None else {}),
        **({"images": scored.written} if scored.written is not None else {}),
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
        )
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
