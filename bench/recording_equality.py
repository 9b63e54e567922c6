"""Whether SLAM logs made from the same frames are equal once decoded: every map snapshot's
Gaussians (every array of every parameter, ids and sums, compared bit for bit), the estimated
and ground-truth poses, the calibration and every per-frame statistic but its timings (`ms`).
The first log is the reference; each other is compared with it. The logs' bytes may differ
(the recorded source path, the run's timings, the topics a recording was read from); what
their results differ in is listed, not judged.

Usage:
    python bench/recording_equality.py folder.mcap ros2.mcap ros2s.mcap ros1.mcap [--json OUT]

Exits 1 when a log differs from the reference in anything compared.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.mcap_log import (
    TOPIC_CALIBRATION,
    TOPIC_POSE,
    TOPIC_POSE_GT,
    TOPIC_STATS,
    LogReader,
)


def bit_equal(a: Any, b: Any) -> bool:
    """Two arrays (or None) equal bit for bit: dtype, shape and bytes."""
    if a is None or b is None:
        return a is None and b is None
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def decoded(path: Path) -> dict[str, Any]:
    """What a log holds once decoded: its snapshots, poses, calibration records and stats."""
    with LogReader(path) as reader:
        snapshots = [reader.read_map(i) for i in range(reader.snapshot_count)]
        poses = {topic: reader.read_poses(topic) for topic in (TOPIC_POSE, TOPIC_POSE_GT)}
        calibration = [m.data for _s, _c, m in reader.iter_messages([TOPIC_CALIBRATION])]
        stats = []
        for _schema, _channel, message in reader.iter_messages([TOPIC_STATS]):
            record = json.loads(message.data)
            record.pop("ms", None)  # (timings)
            stats.append((message.log_time, record))
        results = dict(reader.metadata.results)
    return {
        "snapshots": snapshots,
        "poses": poses,
        "calibration": calibration,
        "stats": stats,
        "results": results,
    }


def compare(reference: dict[str, Any], other: dict[str, Any]) -> dict[str, Any]:
    """What of `other` equals `reference` (see the module docstring)."""
    maps_equal = len(reference["snapshots"]) == len(other["snapshots"])
    differing: list[str] = []
    for k, (a, b) in enumerate(zip(reference["snapshots"], other["snapshots"], strict=False)):
        for f in fields(a):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
                same = bit_equal(x, y)
            else:
                same = x == y
            if not same:
                differing.append(f"snapshot {k}: {f.name}")
    poses = {
        topic: all(
            bit_equal(x, y)
            for x, y in zip(reference["poses"][topic], other["poses"][topic], strict=True)
        )
        for topic in reference["poses"]
    }
    results_differ = sorted(
        key
        for key in set(reference["results"]) | set(other["results"])
        if reference["results"].get(key) != other["results"].get(key)
    )
    last = reference["snapshots"][-1] if reference["snapshots"] else None
    return {
        "snapshots": len(other["snapshots"]),
        "gaussians": None if last is None else len(other["snapshots"][-1]),
        "maps_equal": maps_equal and not differing,
        "differing": differing[:20],
        "poses_equal": poses[TOPIC_POSE],
        "poses": len(other["poses"][TOPIC_POSE][0]),
        "gt_poses_equal": poses[TOPIC_POSE_GT],
        "calibration_equal": reference["calibration"] == other["calibration"],
        "stats_equal": reference["stats"] == other["stats"],
        "stats": len(other["stats"]),
        "results_differ_in": results_differ,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reference", type=Path)
    parser.add_argument("others", type=Path, nargs="+")
    parser.add_argument("--json", type=Path, default=None, help="also write the report here")
    opts = parser.parse_args()
    reference = decoded(opts.reference)
    report = {str(path): compare(reference, decoded(path)) for path in opts.others}
    keys = ("maps_equal", "poses_equal", "gt_poses_equal", "calibration_equal", "stats_equal")
    for path, found in report.items():
        print(
            f"{path}: {found['snapshots']} snapshots ({found['gaussians']} Gaussians), "
            f"{found['poses']} poses, {found['stats']} stats; "
            + ", ".join(f"{k} {found[k]}" for k in keys)
            + f"; results differ in {found['results_differ_in']}"
            + (f"; differing: {found['differing']}" if found["differing"] else "")
        )
    if opts.json is not None:
        opts.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0 if all(all(found[k] for k in keys) for found in report.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
