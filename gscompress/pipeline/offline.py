"""The offline commands: import-ply, prune, share, export-ply, export-traj and info.

numpy + mcap only: nothing here imports torch or the SLAM code, so these commands start fast.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import LogFormatError, OptionError
from gscompress.gaussians import GaussianMap
from gscompress.io.columns import check_precision
from gscompress.io.files import check_output, sha256
from gscompress.io.map_files import map_suffix, read_map_file, write_map_file
from gscompress.io.mcap_log import (
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    TOPIC_POSE_GT,
    LogMetadata,
    LogReader,
    LogWriter,
    Snapshot,
    pointcloud_bytes,
    read_map,
)
from gscompress.io.ply import write_ply
from gscompress.io.trajectory import write_tum_trajectory
from gscompress.ops.budget import Budget
from gscompress.ops.select import check_ratio, select_count, select_top, strategy_scores

log = logging.getLogger(__name__)

QUANTILES = (0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0)


def import_ply(
    src: str | Path, dst: str | Path, *, command: str = "", force: bool = False
) -> dict[str, Any]:
    """Turn a map file of any 3DGS tool (PLY, compressed PLY or SPZ) into a one-snapshot
    gscompress log."""
    check_output(dst, [src], force, ".mcap")
    gaussians = read_map_file(src)
    meta = LogMetadata().derive({"name": "import-ply"}, src, command)
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
    its results are what `transform` returns beside the new map. The new map is stored at the
    precision of the one it replaces (an fp16 share stays fp16).
    """
    check_output(dst, [src], force, ".mcap")
    with LogReader(src) as log_in:
        last = log_in.require_snapshots() - 1
        meta = log_in.metadata.derive(operation, src, command)
        with LogWriter(dst, meta, inputs=[src], force=force) as out:
            snapshot = 0
            for schema, channel, message in log_in.iter_messages():
                if channel.topic != TOPIC_GAUSSIANS:
                    out.copy_message(schema, channel, message)
                    continue
                if snapshot == last:
                    stored = log_in.decode_snapshot(schema, message)
                    new_map, meta.results = transform(stored.gaussians)
                    out.write_gaussians(new_map, message.log_time, stored.precision)
                else:
                    out.copy_message(schema, channel, message)
                snapshot += 1
    return {"output": str(dst), **meta.results}


def share_log(
    src: str | Path,
    dst: str | Path,
    budget: str | float | Budget,
    *,
    strategy: str = "pwas",
    precision: str | None = None,
    seed: int = 0,
    ply: str | Path | None = None,
    command: str = "",
    force: bool = False,
) -> dict[str, Any]:
    """Cut the budgeted top-K share of a log's map for another agent (MCAP, and PLY if asked).

    The share is a small log: the metadata record (source, strategy, budget, counts, provenance)
    and one `/gaussians` snapshot holding the selected Gaussians with all their fields.

    Args:
        src: the log whose map (last snapshot) is shared.
        dst: the share (MCAP).
        budget: a fraction of the Gaussians in (0, 1], or bytes (`"2MB"`, `"1.5MiB"`, see
            `Budget`). A byte budget bounds the serialized `/gaussians` message, which holds the
            most Gaussians that fit.
        strategy: what to rank Gaussians by (`Strategy`).
        precision: "fp32", or "fp16" to send the bounded attributes as float16 (more Gaussians
            per byte; the receiver decodes float32); None: as the source map is stored (a share
            of an fp16 map stays fp16: float32 would only double its bytes).
        seed: seed of the random strategy.
        ply: also write the share as a float32 3DGS PLY (the decoded values).
        command: command line for the provenance record.
        force: overwrite existing outputs.

    Raises:
        InputError: bad budget, precision or strategy (OptionError: --ply equal to the MCAP
            output).
        BudgetError: the budget holds no Gaussian.
        MapError: at fp16, a selected value beyond the float16 range.
    """
    budget = Budget.parse(budget)
    if precision is not None:
        check_precision(precision)
    outputs = [(dst, ".mcap")] if ply is None else [(dst, ".mcap"), (ply, ".ply")]
    if ply is not None and Path(ply).resolve() == Path(dst).resolve():
        raise OptionError("--ply must differ from the MCAP output")
    for path, suffix in outputs:
        check_output(path, [src], force, suffix)
    with LogReader(src) as log_in:
        stored = log_in.read_snapshot()
        meta = log_in.metadata
    full, precision = stored.gaussians, precision or stored.precision
    count = budget.count(len(full), pointcloud_bytes(full, precision, timestamp_ns=0))
    shared, _ = select_count(full, count, strategy, seed)
    operation = {"name": "share", **budget.record(), "strategy": strategy, "seed": seed}
    operation["precision"] = precision
    out_meta = meta.derive(operation, src, command)
    out_meta.results = {
        "source": Path(src).name,
        "strategy": strategy,
        **budget.record(),
        "precision": precision,
        "selected": len(shared),
        "total": len(full),
    }
    with LogWriter(dst, out_meta, inputs=[src], force=force) as out:
        written = out.write_gaussians(shared, 0, precision)
        if budget.budget_bytes is not None and written > budget.budget_bytes:
            raise AssertionError(f"share message of {written} B exceeds {budget.budget_bytes} B")
        out_meta.results["bytes"] = written  # the metadata record is written on close
    if ply is not None:
        try:  # the receiver's values: what the share decodes to (float16-rounded at fp16)
            received = shared if precision == "fp32" else read_map(dst)
            write_ply(received, ply, inputs=(src,), force=force)
        except BaseException:  # a share is written whole or not at all
            Path(dst).unlink(missing_ok=True)
            raise
    return {"output": str(dst), "ply": None if ply is None else str(ply), **out_meta.results}


def export_ply(
    src: str | Path,
    dst: str | Path,
    *,
    snapshot: int = -1,
    importance: bool = True,
    force: bool = False,
) -> dict[str, Any]:
    """Write one snapshot of a log (default the last, "the map") as a 3DGS PLY file, or as SPZ
    when `dst` ends in `.spz` (without scores or ids: SPZ has no place for them)."""
    check_output(dst, [src], force, map_suffix(dst))
    with LogReader(src) as log_in:
        gaussians = log_in.read_map(snapshot)
        index = snapshot % log_in.snapshot_count  # read_map refused one out of range
    write_map_file(gaussians, dst, importance=importance, inputs=(src,), force=force)
    return {"output": str(dst), "gaussians": len(gaussians), "snapshot": index}


def export_trajectory(
    src: str | Path, dst: str | Path, *, ground_truth: bool = False, force: bool = False
) -> dict[str, Any]:
    """Write a log's estimated poses (or, with `ground_truth`, its `/camera/pose_gt`) as a TUM
    trajectory, stamped with the frames' timestamps, for evo and other tools.

    Raises:
        LogFormatError: the log has no such poses (not a SLAM log, or no ground truth).
    """
    topic = TOPIC_POSE_GT if ground_truth else TOPIC_POSE
    check_output(dst, [src], force, ".txt")
    with LogReader(src) as log_in:
        stamps_ns, poses = log_in.read_poses(topic)
    if len(poses) == 0:
        what = "ground-truth poses" if ground_truth else "estimated poses (not a SLAM log?)"
        raise LogFormatError(f"{src} has no {topic} messages: no {what}")
    name = "ground truth" if ground_truth else "estimated trajectory"
    write_tum_trajectory(dst, stamps_ns / 1e9, poses, [f"{name} of {Path(src).name}"])
    return {"output": str(dst), "poses": len(poses), "topic": topic}


def log_info(path: str | Path, *, histogram_bins: int = 10) -> dict[str, Any]:
    """Summarise a log: channels, snapshots, the map, its scores, bytes and provenance.

    `map.bytes` is the serialized `/gaussians` message of the map (what a share sends, the
    quantity a byte budget bounds), `map.packed_bytes` its records alone, `map.record_bytes`
    the bytes per Gaussian and `map.precision` how the float fields are stored.
    """
    path = Path(path)
    with LogReader(path) as log_in:
        channels = [
            {"topic": c.topic, "schema": c.schema, "encoding": c.encoding, "messages": c.messages}
            for c in log_in.channels
        ]
        snapshots: list[dict[str, Any]] = []
        final: Snapshot | None = None
        for schema, _channel, message in log_in.iter_messages([TOPIC_GAUSSIANS]):
            final = log_in.decode_snapshot(schema, message)
            snapshots.append({"log_time_ns": message.log_time, "gaussians": len(final.gaussians)})
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
        "world_frame": meta.world_frame,
        "channels": channels,
        "snapshots": snapshots,
        "provenance": meta.provenance,
        "results": meta.results,
    }
    if final is not None:
        info["map"] = map_summary(final.gaussians, histogram_bins)
        info["map"]["precision"] = final.precision
        info["map"]["bytes"] = final.message_bytes
        info["map"]["record_bytes"] = final.point_stride
        info["map"]["packed_bytes"] = len(final.gaussians) * final.point_stride
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
        # scores span decades (a few Gaussians dominate), so the linear bins put nearly all
        # in the first; the log-spaced ones show the shape (zero scores counted apart)
        positive = scores[scores > 0]
        counts, edges = np.histogram(positive, bins=log_edges(positive, histogram_bins))
        summary["importance_histogram_log"] = {
            "counts": counts.tolist(),
            "edges": edges.tolist(),
            "zeros": int(len(scores) - len(positive)),
        }
        summary["scored"] = int(np.count_nonzero(gaussians.importance_weight > 0))
    return summary


def log_edges(positive: np.ndarray, bins: int) -> np.ndarray:
    """`bins` + 1 log-spaced histogram edges from the smallest to the largest of these positive
    scores (a span of 1% when they are all equal, [1e-6, 1] when there are none)."""
    low, high = (float(positive.min()), float(positive.max())) if len(positive) else (1e-6, 1.0)
    high = max(high, low * 1.01)
    edges = np.logspace(np.log10(low), np.log10(high), bins + 1)
    edges[[0, -1]] = low, high  # exactly: 10 ** log10(x) may round off x and leave it out
    return edges
