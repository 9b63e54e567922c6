"""`gsc score`: PWAS scores for an existing map from a sequence's views (needs torch)."""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.files import check_output
from gscompress.io.mcap_log import (
    POSES_GROUND_TRUTH,
    LogMetadata,
    LogReader,
    LogWriter,
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
    from gscompress.datasets import open_sequence
    from gscompress.importance import resolve_sigma_d, sigma_d_value
    from gscompress.ops.score import score_map
    from gscompress.render import resolve_device

    check_output(dst, [p for p in (src, seq, poses) if p is not None], force, ".mcap")
    if sigma_d is not None and not sigma_d > 0:
        raise InputError(f"`sigma_d` must be above 0 (or inf), got {sigma_d}", options=("sigma_d",))
    is_log = Path(src).suffix.lower() != ".ply"
    if is_log:
        with LogReader(src) as reader:
            reader.require_snapshots()
            meta = reader.metadata
            found = trajectory(reader)
            log_ns, log_poses = found.times_ns, found.T_world_cam
        frames = frames or meta.frames or "all"
        sequence = open_log_sequence(seq, src, meta, frames, size, recording)
    else:
        frames = frames or "all"
        sequence = open_sequence(seq, size=size, frames=frames, recording=recording)
    if poses is None and is_log and len(log_ns):
        positions, index = frames_with_poses(sequence, log_ns, src)
        stamps, T_world_cams = np.asarray(sequence.timestamps)[positions], log_poses[index]
        source = meta.pose_origin()
    else:
        if poses is None and is_log and meta.world_frame.startswith("first-camera:"):
            raise InputError(
                f"{src} has no poses and its world frame is its run's first camera, not the "
                f"ground truth of {sequence.name}: pass --poses TRAJ.txt (in its frame)"
            )
        stamps, T_world_cams = view_poses(sequence, poses)
        source = Path(poses).name if poses else POSES_GROUND_TRUTH
    skipped = len(sequence) - len(stamps)
    if skipped:
        log.warning("%d of the %d frames selected have no pose (%s): scored from the other %d",
                    skipped, len(sequence), source, len(stamps))  # fmt: skip
    depths = (sequence.frame(i).depth for i in range(len(sequence)))
    used_sigma_d = resolve_sigma_d(sigma_d, depths, sequence.intrinsics)
    torch_device = resolve_device(device, backend)

    views = itertools.count(1)
    on_view = None if progress is None else lambda _: progress(next(views), len(T_world_cams))

    def score(gaussians: GaussianMap) -> tuple[GaussianMap, dict[str, Any]]:
        scored = score_map(
            gaussians, T_world_cams, sequence.intrinsics, sigma_d=used_sigma_d, backend=backend,
            device=torch_device, progress=on_view,
        )  # fmt: skip
        seen = int(np.count_nonzero(scored.importance_weight > 0))
        results = {"views": len(T_world_cams), "gaussians": len(scored), "scored": seen,
                   "sigma_d": sigma_d_value(used_sigma_d)}  # fmt: skip
        return scored, {**results, "frames_without_pose": skipped, "poses": source}

    operation = {
        "name": "score",
        "sequence": sequence.name,
        "frames": frames,
        "poses": source,
        "sigma_d": "auto" if sigma_d is None else sigma_d_value(sigma_d),
        "size": [sequence.intrinsics.width, sequence.intrinsics.height],
    }
    if is_log:
        return rewrite_map(src, dst, operation, score, command=command, force=force)
    scored, results = score(read_ply(src))
    meta = LogMetadata(sequence=sequence.name, frames=frames).derive(operation, src, command)
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
                f"{sequence.name} has no ground-truth poses; pass --poses TRAJ.txt (TUM format)"
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
