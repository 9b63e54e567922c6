"""`gsc info` of a log: its channels, snapshots, map, scores, bytes and provenance (numpy +
mcap only, never torch; a recording's side is `gscompress.pipeline.recordings`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gscompress.gaussians import GaussianMap
from gscompress.io.files import sha256
from gscompress.io.mcap_log import TOPIC_GAUSSIANS, LogReader, Snapshot
from gscompress.selection import strategy_scores

QUANTILES = (0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0)


def log_info(path: str | Path, *, histogram_bins: int = 10) -> dict[str, Any]:
    """Summarise a log: channels, snapshots, the map, its scores, bytes and provenance.

    `map.bytes` is the serialized `/gaussians` message of the map, `map.bytes_per_gaussian`
    that per Gaussian and `map.codec` how it is stored (fp32, fp16 or compact); each snapshot
    says the same. `file_bytes` is the whole file (what a byte budget bounds for a share).
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
            snapshots.append(
                {
                    "log_time_ns": message.log_time,
                    "gaussians": len(final.gaussians),
                    "codec": final.codec,
                    "bytes": final.message_bytes,
                }
            )
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
        info["map"]["codec"] = final.codec
        info["map"]["bytes"] = final.message_bytes
        info["map"]["bytes_per_gaussian"] = final.bytes_per_gaussian
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
