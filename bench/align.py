"""Time of `gsc align`'s aligner on two maps of about 50k Gaussians each, and its error.

The two maps are made from two agents' logs (e.g. the halves of a sequence, each agent at the
identity at its own first frame): every opaque Gaussian is drawn `--samples` times from its own
3D normal (centre, scale), which keeps the scene and multiplies the count. The reference
transform is the one between the agents' ground-truth first-frame poses. Prints one JSON
object: Gaussians, wall and CPU seconds of each alignment (`--repeat` of them; CPU seconds add
up all threads), the error, and the load average (a shared, loaded machine is slower).

    python bench/align.py A.mcap B.mcap --samples 8
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from gscompress.io.mcap_log import TOPIC_POSE_GT, LogReader
from gscompress.ops.align import AlignOptions, Cloud, align_clouds, transform_error
from gscompress.pipeline.aligning import log_cloud


def first_gt_pose(path: str) -> np.ndarray:
    with LogReader(path) as log:
        _, poses = log.read_poses(TOPIC_POSE_GT)
    return poses[0]


def denser(cloud: Cloud, scales: np.ndarray, samples: int, seed: int) -> Cloud:
    """`samples` draws around every centre, at its Gaussian's scale."""
    rng = np.random.default_rng(seed)
    pts = np.repeat(cloud.points, samples, axis=0)
    sd = np.repeat(scales, samples, axis=0)
    pts = pts + rng.normal(size=pts.shape) * sd[:, None]
    return Cloud(pts, np.repeat(cloud.colors, samples, axis=0), viewpoints=cloud.viewpoints)


def log_scales(path: str) -> np.ndarray:
    with LogReader(path) as log:
        m = log.read_map()
    keep = m.opacities() >= 0.3
    return m.scales()[keep].min(axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("source")
    parser.add_argument("target")
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    T_true = np.linalg.inv(first_gt_pose(args.target)) @ first_gt_pose(args.source)
    src = denser(log_cloud(args.source)[0], log_scales(args.source), args.samples, 0)
    tgt = denser(log_cloud(args.target)[0], log_scales(args.target), args.samples, 1)
    runs = []
    for seed in range(args.repeat):
        started, cpu = time.perf_counter(), time.process_time()
        result = align_clouds(src, tgt, AlignOptions(seed=seed))
        seconds, cpu = time.perf_counter() - started, time.process_time() - cpu
        dt, dr = transform_error(result.T_target_source, T_true)
        run = {
            "seconds": seconds,
            "cpu_seconds": cpu,
            "error_cm": 100 * dt,
            "error_deg": dr,
            "overlap": result.overlap,
            "voxel": result.voxel,
        }
        runs.append({k: round(v, 4) for k, v in run.items()})
    print(
        json.dumps(
            {
                "source": args.source,
                "target": args.target,
                "gaussians": [len(src.points), len(tgt.points)],
                "runs": runs,
                "median_seconds": float(np.median([r["seconds"] for r in runs])),
                "cpus": os.cpu_count(),
                "loadavg": os.getloadavg(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
