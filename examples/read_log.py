"""Reading a gscompress log in Python: metadata, trajectory, map snapshots and per-frame stats.

Everything here is numpy and mcap (no torch), so it runs wherever the package is installed.

Usage: python examples/read_log.py LOG.mcap [--tum TRAJ.txt [--force]] [--top 5]
  e.g. python examples/read_log.py demo_out/map.mcap --tum demo_out/estimate.txt
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gscompress.errors import GscError
from gscompress.io.mcap_log import TOPIC_GAUSSIANS, TOPIC_POSE, TOPIC_STATS, LogReader
from gscompress.pipeline import export_trajectory


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("--tum", type=Path, help="write the estimated trajectory as TUM text")
    parser.add_argument("--force", action="store_true", help="overwrite the --tum file")
    parser.add_argument("--top", type=int, default=5, help="how many top Gaussians to list")
    opts = parser.parse_args()
    try:
        show(opts)
    except GscError as exc:  # (the library's errors: one line, as gsc prints them)
        raise SystemExit(f"error: {exc}") from None


def show(opts: argparse.Namespace) -> None:
    """Print what the log holds."""
    with LogReader(opts.log) as log:
        meta = log.metadata
        print(f"{opts.log}: written by gscompress {meta.tool_version}: {meta.command}")
        print(f"sequence {meta.sequence}, frames {meta.frames}, world frame {meta.world_frame}")
        for step in meta.provenance:  # each derivation (prune, share, merge, inject) and its parent
            print(f"  derived by {step['operation']['name']} from {step.get('parent')}")
        for channel in log.channels:
            print(f"  {channel.topic:<22} {channel.messages:>5} messages")

        # the trajectory: log times in ns and camera-to-world 4x4 poses
        stamps_ns, poses = log.read_poses(TOPIC_POSE)
        if len(poses):
            steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
            seconds = (stamps_ns[-1] - stamps_ns[0]) / 1e9
            print(f"trajectory: {len(poses)} poses over {seconds:.2f} s, path {steps.sum():.3f} m")
        else:
            print("trajectory: none (no /camera/pose messages: a share, or an imported map)")
        if opts.tum:  # as `gsc export-traj` writes it (and refuses what it refuses)
            export_trajectory(opts.log, opts.tum, force=opts.force)
            print(f"  written to {opts.tum}")

        # every snapshot of the map, with the event its stats record names (stage, checkpoint);
        # the last one is the map
        events = {m.log_time: json.loads(m.data) for _, _, m in log.iter_messages([TOPIC_STATS])}
        for i, (schema, _, message) in enumerate(log.iter_messages([TOPIC_GAUSSIANS])):
            what = events.get(message.log_time, {}).get("event", "the map")
            print(f"  snapshot {i}: {len(log.decode_map(schema, message)):>7} Gaussians ({what})")

        # the map: the last snapshot, raw parameters plus activated views of them
        gaussians = log.read_map()
    print(
        f"map: {len(gaussians)} Gaussians, isotropic {gaussians.isotropic}, "
        f"SH degree {gaussians.sh_degree}"
    )
    if not gaussians.has_importance or len(gaussians) == 0:
        return
    importance = gaussians.importance
    q = np.quantile(importance, [0.1, 0.5, 0.9])
    print(f"PWAS importance: 10% {q[0]:.4g}, median {q[1]:.4g}, 90% {q[2]:.4g}")
    top = np.argsort(-importance, kind="stable")[: opts.top]
    scales, opacities, colors = gaussians.scales(), gaussians.opacities(), gaussians.colors()
    for i in top:
        x, y, z = gaussians.means[i]
        r, g, b = colors[i]
        print(
            f"  id {gaussians.ids[i]:>6}: at ({x:+.3f}, {y:+.3f}, {z:+.3f}) m, scale "
            f"{scales[i].max() * 100:.2f} cm, opacity {opacities[i]:.2f}, "
            f"rgb ({r:.2f}, {g:.2f}, {b:.2f}), importance {importance[i]:.4g}"
        )


if __name__ == "__main__":
    main()
