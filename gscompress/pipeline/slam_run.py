"""`gsc slam`: a sequence through the SLAM system into a log (DESIGN.md section 6)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import InputError
from gscompress.io.files import check_output
from gscompress.io.mcap_log import (
    LogMetadata,
    LogWriter,
)
from gscompress.ops.select import check_ratio
from gscompress.pipeline.offline import seconds_to_ns


def slam_file(
    seq: str | Path | None,
    dst: str | Path,
    *,
    preset: str = "cpu",
    config_path: str | Path | None = None,
    frames: str = "all",
    size: tuple[int, int] | None = None,
    device: str = "auto",
    keep: float | None = None,
    no_prune: bool = False,
    command: str = "",
    force: bool = False,
    progress: Callable[[int, int, dict[str, Any]], object] | None = None,
    sequence: Any = None,
) -> dict[str, Any]:
    """Run SLAM over a sequence and write the log (DESIGN.md section 6).

    The log holds the calibration, one `/camera/pose` (+ `/tf`) and `/slam/stats` record per
    frame, `/camera/pose_gt` where the sequence has ground truth, a `/gaussians` snapshot after
    each PWAS pruning stage and one at the end ("the map"), and the metadata record (full config,
    sequence, frames, command, results). Each frame is flushed to disk as soon as it is done.
    On KeyboardInterrupt the map so far is written as the final snapshot, the log is closed
    (valid and readable, results marked `interrupted`) and the interrupt is raised again.

    Args:
        seq: the sequence folder (None when `sequence` is given).
        dst: the output log (.mcap).
        preset: starting configuration (`gscompress.slam.config.PRESETS`).
        config_path: a YAML config applied on top of the preset.
        frames: frame subset (all, odd, even, START:STOP:STEP).
        size: working size (W, H), overriding the config's.
        device: torch device, or "auto".
        keep: PWAS keep ratio of the pruning stages, overriding the config's.
        no_prune: skip the PWAS pruning stages (cyclic opacity cleanup still runs).
        command: the command line, for the metadata.
        force: overwrite `dst`.
        progress: called after every frame with (frames done, total, the frame's stats).
        sequence: an already opened `RGBDSequence` (e.g. an in-memory synthetic one) instead
            of `seq`; `frames` and `size` are then not applied to it.

    Returns:
        Output path, frame and Gaussian counts, seconds per frame, ATE (cm) when the sequence
        has ground truth, and whether the run was interrupted.
    """
    import time

    from gscompress.datasets import open_sequence
    from gscompress.metrics import ate_rmse_cm
    from gscompress.slam.config import resolve_config
    from gscompress.slam.system import SlamSystem

    if sequence is None and seq is None:
        raise InputError("slam_file needs a sequence folder or an opened sequence")
    inputs = [seq] if sequence is None and seq is not None else []
    check_output(dst, inputs, force)
    if keep is not None:
        check_ratio(keep, "--keep")
    config = resolve_config(preset, config_path, size=size, keep=keep, no_prune=no_prune)
    if sequence is None:
        assert seq is not None
        sequence = open_sequence(seq, size=config.size, frames=frames)
    total = len(sequence)
    if total == 0:
        raise InputError(f"{getattr(sequence, 'name', seq)}: no frames selected ({frames})")
    system = SlamSystem(config, sequence.intrinsics, device, total_frames=total)
    meta = LogMetadata(
        command=command, config=config.to_dict(), sequence=sequence.name, frames=str(frames)
    )
    gt_poses: list[np.ndarray] = []
    est_poses: list[np.ndarray] = []
    interrupted: KeyboardInterrupt | None = None
    start = time.perf_counter()
    t_ns = 0
    with LogWriter(dst, meta, inputs=inputs, force=force) as out:
        out.write_calibration(sequence.intrinsics, 0)
        out.flush()
        try:
            for i in range(total):
                frame = sequence.frame(i)
                result = system.process(frame)
                t_ns = seconds_to_ns(frame.timestamp)
                out.write_pose(result.T_world_cam, t_ns)
                if frame.T_world_cam is not None:
                    out.write_pose(frame.T_world_cam, t_ns, ground_truth=True)
                    gt_poses.append(frame.T_world_cam)
                    est_poses.append(result.T_world_cam)
                stats = result.stats()
                out.write_stats(stats, t_ns)
                if result.event:
                    out.write_gaussians(system.gaussian_map(), t_ns)
                out.flush()
                if progress is not None:
                    progress(i + 1, total, stats)
        except KeyboardInterrupt as exc:
            interrupted = exc
        done = len(system.poses)
        seconds = time.perf_counter() - start
        gaussians = system.gaussian_map()
        out.write_gaussians(gaussians, t_ns)
        meta.results = {
            "frames": done,
            "frames_total": total,
            "gaussians": len(gaussians),
            "seconds": round(seconds, 3),
            "seconds_per_frame": round(seconds / max(done, 1), 4),
            "interrupted": interrupted is not None,
        }
        if len(gt_poses) >= 2:
            meta.results["ate_rmse_cm"] = ate_rmse_cm(np.array(gt_poses), np.array(est_poses))
    if interrupted is not None:
        raise interrupted
    return {"output": str(dst), **meta.results}
