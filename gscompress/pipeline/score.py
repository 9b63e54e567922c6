"""`gsc score`: PWAS scores for an existing map from a sequence's views (needs torch)."""

from __future__ import annotations

import functools
import itertools
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from gscompress.errors import InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.files import check_output
from gscompress.io.mcap_log import (
    POSES_GROUND_TRUTH,
    LogMetadata,
    LogReader,
    LogWriter,
    Trajectory,
    seconds_to_ns,
)
from gscompress.io.ply import read_ply
from gscompress.pipeline.logs import (
    frames_with_poses,
    open_log_sequence,
    pose_source,
    rewrite_map,
    trajectory,
)

log = logging.getLogger(__name__)


def score_file(
    src: str | Path,
    dst: str | Path,
    seq: str | Path,
    *,
    poses: str | Path | None = None,
    frames: str | None = None,
    size: tuple[int, int] | None = None,
    sigma_d: float | None = None,
    backend: str = "auto",
    device: str = "auto",
    command: str = "",
    force: bool = False,
    progress: Callable[[int, int], object] | None = None,
    recording: Any = None,
) -> dict[str, Any]:
    """PWAS-score the map in `src` (a log or a 3DGS PLY) from the views of sequence `seq`.

    The map is rendered, not optimised, from every selected frame, at the pose `poses` (a TUM
    trajectory) gives for its timestamp; without it, at the log's own estimated pose
    (`/camera/pose`, frames without one skipped), else at the ground-truth pose. A log's frame
    subset and working size are the defaults, as its run had them (a PLY's: every frame, the
    sequence's own size). An MCAP input is copied with its map replaced by the scored one; a PLY
    input becomes a new log with calibration, the view poses and the scored map. Needs torch
    (the renderer). `progress(done, total)` is called after each view.

    `sigma_d` (metres; inf: no proximity weighting) None derives it from the scene as `gsc slam`
    does (`gscompress.importance.resolve_sigma_d`): the median camera-to-surface distance of the
    first selected frame with valid depth. The value used is in the results (`sigma_d`).
    `recording`: a recording's `RecordingOptions` (None: a log's recorded ones, else chosen).

    Raises:
        InputError: a log without poses whose world frame is its first camera (the ground
            truth is not in that frame; pass `poses`).
    """
    from gscompress.importance import resolve_sigma_d, sigma_d_value
    from gscompress.render import resolve_device

    check_output(dst, [p for p in (src, seq, poses) if p is not None], force, ".mcap")
    if sigma_d is not None and not sigma_d > 0:
        raise InputError(f"`sigma_d` must be above 0 (or inf), got {sigma_d}", options=("sigma_d",))
    opened = _open_input(src, seq, frames, size, recording)
    sequence = opened.sequence
    stamps, T_world_cams, source = _poses_to_score_from(src, poses, opened)
    skipped = len(sequence) - len(stamps)
    if skipped:
        log.warning(
            "%d of the %d frames selected have no pose (%s): scored from the other %d",
            skipped,
            len(sequence),
            source,
            len(stamps),
        )
    depths = (sequence.frame(i).depth for i in range(len(sequence)))
    used_sigma_d = resolve_sigma_d(sigma_d, depths, sequence.intrinsics)
    torch_device = resolve_device(device, backend)

    views = itertools.count(1)
    on_view = None if progress is None else lambda _: progress(next(views), len(T_world_cams))
    score = functools.partial(
        _scored,
        T_world_cams=T_world_cams,
        intrinsics=sequence.intrinsics,
        sigma_d=used_sigma_d,
        backend=backend,
        device=torch_device,
        progress=on_view,
        extra={"frames_without_pose": skipped, "poses": source},
    )
    operation = {
        "name": "score",
        "sequence": sequence.name,
        "frames": opened.frames,
        "poses": source,
        "sigma_d": "auto" if sigma_d is None else sigma_d_value(sigma_d),
        "size": [sequence.intrinsics.width, sequence.intrinsics.height],
    }
    if opened.meta is not None:
        return rewrite_map(src, dst, operation, score, command=command, force=force)
    return _scored_map_log(
        src, dst, score, operation, opened, (stamps, T_world_cams), command, force
    )


class _Opened(NamedTuple):
    """What `score_file` scores from: the sequence, its frame subset, and a log's metadata and
    trajectory (both None for a PLY)."""

    sequence: Any
    frames: str
    meta: LogMetadata | None
    found: Trajectory | None


def _open_input(
    src: str | Path,
    seq: str | Path,
    frames: str | None,
    size: tuple[int, int] | None,
    recording: Any,
) -> _Opened:
    """The sequence as a log's run had it (`open_log_sequence`), or for a PLY as asked (every
    frame, the sequence's own size by default), with the log's metadata and trajectory."""
    from gscompress.datasets import open_sequence

    if Path(src).suffix.lower() != ".ply":
        with LogReader(src) as reader:
            reader.require_snapshots()
            meta = reader.metadata
            found = trajectory(reader)
        frames = frames or meta.frames or "all"
        sequence = open_log_sequence(seq, src, meta, frames, size, recording)
        return _Opened(sequence, frames, meta, found)
    frames = frames or "all"
    sequence = open_sequence(seq, size=size, frames=frames, recording=recording)
    return _Opened(sequence, frames, None, None)


def _poses_to_score_from(
    src: str | Path, poses: str | Path | None, opened: _Opened
) -> tuple[np.ndarray, np.ndarray, str]:
    """(timestamps, camera-to-world poses, where they came from) of the views to score from:
    the log's own poses of its frames that have one unless `poses` is given, else
    `view_poses`'s.

    Raises:
        InputError: a log without poses whose world frame is its first camera.
    """
    sequence, meta, found = opened.sequence, opened.meta, opened.found
    if poses is None and meta is not None and found is not None and len(found.times_ns):
        positions, index = frames_with_poses(sequence, found.times_ns, src)
        stamps, T_world_cams = np.asarray(sequence.timestamps)[positions], found.T_world_cam[index]
        return stamps, T_world_cams, meta.pose_origin()
    if poses is None and meta is not None and meta.world_frame.startswith("first-camera:"):
        raise InputError(
            f"{src} has no poses and its world frame is its run's first camera, not the "
            f"ground truth of {sequence.name}: pass `poses` TRAJ.txt (in its frame)",
            options=("poses",),
        )
    stamps, T_world_cams = view_poses(sequence, poses)
    return stamps, T_world_cams, Path(poses).name if poses else POSES_GROUND_TRUTH


def _scored(
    gaussians: GaussianMap,
    T_world_cams: np.ndarray,
    intrinsics: Any,
    sigma_d: Any,
    backend: str,
    device: Any,
    progress: Callable[[Any], object] | None,
    extra: dict[str, Any],
) -> tuple[GaussianMap, dict[str, Any]]:
    """`gaussians` PWAS-scored from the views (`score_map`), and the results: views, Gaussians,
    how many were seen, the `sigma_d` used, then `extra`."""
    from gscompress.importance import sigma_d_value
    from gscompress.ops.score import score_map

    scored = score_map(
        gaussians,
        T_world_cams,
        intrinsics,
        sigma_d=sigma_d,
        backend=backend,
        device=device,
        progress=progress,
    )
    seen = int(np.count_nonzero(scored.importance_weight > 0))
    results = {
        "views": len(T_world_cams),
        "gaussians": len(scored),
        "scored": seen,
        "sigma_d": sigma_d_value(sigma_d),
    }
    return scored, {**results, **extra}


def _scored_map_log(
    src: str | Path,
    dst: str | Path,
    score: Callable[[GaussianMap], tuple[GaussianMap, dict[str, Any]]],
    operation: dict[str, Any],
    opened: _Opened,
    views: tuple[np.ndarray, np.ndarray],
    command: str,
    force: bool,
) -> dict[str, Any]:
    """A PLY's map scored (`score`) as a new log: the calibration, the poses of the `views`
    (timestamps and poses) and the scored map."""
    sequence, (stamps, T_world_cams) = opened.sequence, views
    scored, results = score(read_ply(src))
    meta = LogMetadata(sequence=sequence.name, frames=opened.frames).derive(operation, src, command)
    meta.results = results
    with LogWriter(dst, meta, inputs=[src], force=force) as out:
        out.write_calibration(sequence.intrinsics, 0)
        for stamp, T in zip(stamps, T_world_cams, strict=True):
            out.write_pose(T, seconds_to_ns(stamp))
        out.write_gaussians(scored, seconds_to_ns(stamps[-1]) if len(stamps) else 0)
    return {"output": str(dst), **results}


def view_poses(sequence: Any, poses: str | Path | None) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps [M], camera-to-world [M, 4, 4]) of a sequence's selected frames.

    From the sequence's ground truth, or from `poses` (a TUM trajectory, or a log's estimated
    poses) matched to every frame by time (`gscompress.pipeline.logs.frames_with_poses`).

    Raises:
        DatasetError: no ground truth (without `poses`), or a frame without a pose in `poses`.
    """
    from gscompress.errors import DatasetError

    if poses is None:
        if not sequence.has_ground_truth:
            raise DatasetError(
                f"{sequence.name} has no ground-truth poses; pass `poses` TRAJ.txt (TUM format)",
                options=("poses",),
            )
        stamps, T = sequence.ground_truth()
        return np.asarray(stamps), np.asarray(T)
    times_ns, T_world_cams, tolerance_ns, _ = pose_source(poses)
    positions, index = frames_with_poses(sequence, times_ns, poses, tolerance_ns)
    stamps = np.asarray(sequence.timestamps)
    if len(positions) < len(stamps):
        missing = float(stamps[np.setdiff1d(np.arange(len(stamps)), positions)[0]])
        raise DatasetError(
            f"{poses} has no pose within {tolerance_ns / 1e9:g} s of frame time {missing:.6f}"
        )
    return stamps, T_world_cams[index]
