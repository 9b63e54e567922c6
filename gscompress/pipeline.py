"""Glue between files and the pure core: each function here is one `gsc` command's work.

Functions take paths and options, read inputs through `gscompress.io`, call the pure operations
in `gscompress.ops`, and write outputs atomically. They return a small dict of results that the
CLI prints. Nothing here prints or exits. The offline functions (info, prune, share, export,
import) import neither torch nor the SLAM code.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.files import check_output, sha256
from gscompress.io.mcap_log import (
    TOPIC_GAUSSIANS,
    LogMetadata,
    LogReader,
    LogWriter,
    record_size,
)
from gscompress.io.ply import read_ply, write_ply
from gscompress.ops.select import check_ratio, select_top, strategy_scores

log = logging.getLogger(__name__)

QUANTILES = (0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0)


def import_ply(
    src: str | Path, dst: str | Path, *, command: str = "", force: bool = False
) -> dict[str, Any]:
    """Turn a 3DGS PLY map (from any tool) into a one-snapshot gscompress log."""
    check_output(dst, [src], force)
    gaussians = read_ply(src)
    meta = LogMetadata(command=command).derive({"name": "import-ply"}, src)
    meta.results = {"gaussians": len(gaussians), "scored": gaussians.has_importance}
    with LogWriter(dst, meta, inputs=[src], force=force) as out:
        out.write_gaussians(gaussians, 0)
    return {"output": str(dst), **meta.results}


def prune_log(
    src: str | Path,
    dst: str | Path,
    keep: float,
    *,
    by: str = "pwas",
    seed: int = 0,
    command: str = "",
    force: bool = False,
) -> dict[str, Any]:
    """Keep the `keep` fraction of a log's map with the highest `by` scores.

    The last `/gaussians` snapshot is replaced by its pruned version (same log time); every other
    message, earlier snapshots included, passes through unchanged.
    """
    check_ratio(keep, "--keep")

    def prune(full: GaussianMap) -> tuple[GaussianMap, dict[str, Any]]:
        kept, _ = select_top(full, keep, by, seed)
        return kept, {"kept": len(kept), "total": len(full)}

    operation = {"name": "prune", "keep": keep, "by": by, "seed": seed}
    return rewrite_map(src, dst, operation, prune, command=command, force=force)


def rewrite_map(
    src: str | Path,
    dst: str | Path,
    operation: dict[str, Any],
    transform: Callable[[GaussianMap], tuple[GaussianMap, dict[str, Any]]],
    *,
    command: str = "",
    force: bool = False,
) -> dict[str, Any]:
    """Copy a log, replacing its map (the last snapshot) by `transform(map)`.

    Every other message passes through unchanged; the output's provenance gains `operation` and
    its results are what `transform` returns beside the new map.
    """
    check_output(dst, [src], force)
    with LogReader(src) as log_in:
        last = log_in.require_snapshots() - 1
        meta = log_in.metadata.derive(operation, src)
        meta.command = command
        with LogWriter(dst, meta, inputs=[src], force=force) as out:
            snapshot = 0
            for schema, channel, message in log_in.iter_messages():
                if channel.topic != TOPIC_GAUSSIANS:
                    out.copy_message(schema, channel, message)
                    continue
                if snapshot == last:
                    new_map, meta.results = transform(log_in.decode_map(schema, message))
                    out.write_gaussians(new_map, message.log_time)
                else:
                    out.copy_message(schema, channel, message)
                snapshot += 1
    return {"output": str(dst), **meta.results}


def share_log(
    src: str | Path,
    dst: str | Path,
    budget: float,
    *,
    strategy: str = "pwas",
    seed: int = 0,
    ply: str | Path | None = None,
    command: str = "",
    force: bool = False,
) -> dict[str, Any]:
    """Cut the budgeted top-K share of a log's map for another agent (MCAP, and PLY if asked).

    The share is a small log: the metadata record (source, strategy, budget, counts, provenance)
    and one `/gaussians` snapshot holding the selected Gaussians with all their fields.
    """
    check_ratio(budget, "--budget")
    outputs = [dst] if ply is None else [dst, ply]
    if ply is not None and Path(ply).resolve() == Path(dst).resolve():
        raise InputError("--ply must differ from the MCAP output")
    for path in outputs:
        check_output(path, [src], force)
    with LogReader(src) as log_in:
        full = log_in.read_map()
        meta = log_in.metadata
    shared, _ = select_top(full, budget, strategy, seed)
    operation = {"name": "share", "budget": budget, "strategy": strategy, "seed": seed}
    out_meta = meta.derive(operation, src)
    out_meta.command = command
    out_meta.results = {
        "source": Path(src).name,
        "strategy": strategy,
        "budget": budget,
        "selected": len(shared),
        "total": len(full),
    }
    with LogWriter(dst, out_meta, inputs=[src], force=force) as out:
        out.write_gaussians(shared, 0)
    if ply is not None:
        write_ply(shared, ply, inputs=(src,), force=force)
    return {"output": str(dst), "ply": None if ply is None else str(ply), **out_meta.results}


def export_ply(
    src: str | Path,
    dst: str | Path,
    *,
    snapshot: int = -1,
    importance: bool = True,
    force: bool = False,
) -> dict[str, Any]:
    """Write one snapshot of a log (default the last, "the map") as a 3DGS PLY file."""
    check_output(dst, [src], force)
    with LogReader(src) as log_in:
        gaussians = log_in.read_map(snapshot)
    write_ply(gaussians, dst, importance=importance, inputs=(src,), force=force)
    return {"output": str(dst), "gaussians": len(gaussians), "snapshot": snapshot}


def log_info(path: str | Path, *, histogram_bins: int = 10) -> dict[str, Any]:
    """Summarise a log: channels, snapshots, the map, its scores, bytes and provenance."""
    path = Path(path)
    with LogReader(path) as log_in:
        channels = [
            {"topic": c.topic, "schema": c.schema, "encoding": c.encoding, "messages": c.messages}
            for c in log_in.channels
        ]
        snapshots: list[dict[str, Any]] = []
        final: GaussianMap | None = None
        final_bytes = 0
        for schema, _channel, message in log_in.iter_messages([TOPIC_GAUSSIANS]):
            final = log_in.decode_map(schema, message)
            final_bytes = len(message.data)  # the serialized PointCloud, as it would be sent
            snapshots.append({"log_time_ns": message.log_time, "gaussians": len(final)})
        meta = log_in.metadata
    info: dict[str, Any] = {
        "path": str(path),
        "file_bytes": path.stat().st_size,
        "sha256": sha256(path),
        "profile_version": meta.profile_version,
        "tool_version": meta.tool_version,
        "command": meta.command,
        "sequence": meta.sequence,
        "frames": meta.frames,
        "channels": channels,
        "snapshots": snapshots,
        "provenance": meta.provenance,
        "results": meta.results,
    }
    if final is not None:
        info["map"] = map_summary(final, histogram_bins)
        info["map"]["bytes"] = final_bytes
        info["map"]["packed_bytes"] = len(final) * record_size(final)
    return info


def map_summary(gaussians: GaussianMap, histogram_bins: int = 10) -> dict[str, Any]:
    """Counts, layout, bounds and score statistics of a map (JSON-ready)."""
    summary: dict[str, Any] = {
        "gaussians": len(gaussians),
        "isotropic": gaussians.isotropic,
        "sh_degree": gaussians.sh_degree,
        "has_importance": gaussians.has_importance,
    }
    if len(gaussians):
        summary["bounds_min"] = gaussians.means.min(axis=0).tolist()
        summary["bounds_max"] = gaussians.means.max(axis=0).tolist()
        summary["opacity_mean"] = float(gaussians.opacities().mean())
    if gaussians.has_importance and len(gaussians):
        scores = strategy_scores(gaussians, "pwas")
        summary["importance_quantiles"] = {
            f"q{round(q * 100):02d}": float(v)
            for q, v in zip(QUANTILES, np.quantile(scores, QUANTILES), strict=True)
        }
        counts, edges = np.histogram(scores, bins=histogram_bins)
        summary["importance_histogram"] = {"counts": counts.tolist(), "edges": edges.tolist()}
        summary["scored"] = int(np.count_nonzero(gaussians.importance_weight > 0))
    return summary


def score_file(
    src: str | Path,
    dst: str | Path,
    seq: str | Path,
    *,
    poses: str | Path | None = None,
    frames: str = "all",
    size: tuple[int, int] | None = None,
    sigma_d: float = 20.0,
    backend: str = "auto",
    command: str = "",
    force: bool = False,
    progress: Callable[[int], object] | None = None,
) -> dict[str, Any]:
    """PWAS-score the map in `src` (a log or a 3DGS PLY) from the views of sequence `seq`.

    The map is rendered, not optimised, from every selected frame at its ground-truth pose or
    at the pose `poses` (a TUM trajectory) gives for its timestamp. An MCAP input is copied with
    its map replaced by the scored one; a PLY input becomes a new log with calibration, the view
    poses and the scored map. Needs torch (the renderer).
    """
    from gscompress.datasets import open_sequence
    from gscompress.importance import PwasConfig
    from gscompress.ops.score import score_map

    check_output(dst, [src], force)
    if not sigma_d > 0:
        raise InputError(f"--sigma-d must be positive, got {sigma_d}")
    sequence = open_sequence(seq, size=size, frames=frames)
    stamps, T_world_cams = view_poses(sequence, poses)
    config = PwasConfig(sigma_d=sigma_d)

    def score(gaussians: GaussianMap) -> tuple[GaussianMap, dict[str, Any]]:
        scored = score_map(
            gaussians, T_world_cams, sequence.intrinsics, config, backend=backend, progress=progress
        )
        seen = int(np.count_nonzero(scored.importance_weight > 0))
        return scored, {"views": len(T_world_cams), "gaussians": len(scored), "scored": seen}

    operation = {
        "name": "score",
        "sequence": sequence.name,
        "frames": str(frames),
        "poses": Path(poses).name if poses else "ground truth",
        "sigma_d": sigma_d,
        "size": list(size) if size else None,
    }
    if Path(src).suffix.lower() != ".ply":
        return rewrite_map(src, dst, operation, score, command=command, force=force)
    scored, results = score(read_ply(src))
    meta = LogMetadata(command=command, sequence=sequence.name, frames=str(frames))
    meta = meta.derive(operation, src)
    meta.command, meta.results = command, results
    with LogWriter(dst, meta, inputs=[src], force=force) as out:
        out.write_calibration(sequence.intrinsics, 0)
        for stamp, T in zip(stamps, T_world_cams, strict=True):
            out.write_pose(T, seconds_to_ns(stamp))
        out.write_gaussians(scored, seconds_to_ns(stamps[-1]) if len(stamps) else 0)
    return {"output": str(dst), **results}


def view_poses(sequence: Any, poses: str | Path | None) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps [M], camera-to-world [M, 4, 4]) of a sequence's selected frames.

    From the sequence's ground truth, or from the TUM trajectory `poses` associated to the
    frames by nearest timestamp (within 0.02 s).
    """
    from gscompress.errors import DatasetError
    from gscompress.io.trajectory import read_tum_trajectory

    if poses is None:
        if not sequence.has_ground_truth:
            raise DatasetError(
                f"{sequence.name} has no ground-truth poses; pass --poses TRAJ.txt (TUM format)"
            )
        stamps, T = sequence.ground_truth()
        return np.asarray(stamps), np.asarray(T)
    trajectory = read_tum_trajectory(poses)
    stamps = np.asarray(sequence.timestamps)
    if len(trajectory) == 0:
        raise DatasetError(f"{poses} holds no poses")
    order = np.argsort(trajectory.timestamps)
    t_sorted = trajectory.timestamps[order]
    pos = np.clip(np.searchsorted(t_sorted, stamps), 1, max(len(t_sorted) - 1, 1))
    left = np.clip(pos - 1, 0, len(t_sorted) - 1)
    right = np.clip(pos, 0, len(t_sorted) - 1)
    nearest = np.where(
        np.abs(t_sorted[left] - stamps) <= np.abs(t_sorted[right] - stamps), left, right
    )
    gap = np.abs(t_sorted[nearest] - stamps)
    if np.any(gap > 0.02):
        worst = float(stamps[int(np.argmax(gap))])
        raise DatasetError(f"{poses} has no pose within 0.02 s of frame time {worst:.6f}")
    return stamps, trajectory.T_world_cam[order[nearest]]


def seconds_to_ns(seconds: float) -> int:
    """Integer nanoseconds (log times) from seconds."""
    return round(float(seconds) * 1e9)


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
