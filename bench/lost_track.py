"""How far a run's frames come from being judged lost (docs/recordings.md, "Lost tracks").

Runs `gsc slam`'s system on a sequence and reports, per tracked frame, its depth error after
tracking, the running level it is judged against and their ratio, whether it was re-localised,
and at the end the largest ratio, the ATE and where the run stopped if it did.

    python bench/lost_track.py SEQ [--frames all] [--preset cpu] [--threads 1] [--per-frame]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from gscompress.datasets import open_sequence
from gscompress.errors import TrackingLostError
from gscompress.metrics import ate_rmse_cm
from gscompress.slam.config import preset
from gscompress.slam.system import SlamSystem


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("seq")
    parser.add_argument("--frames", default="all")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--per-frame", action="store_true", help="print every frame's record")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = preset(args.preset)
    sequence = open_sequence(args.seq, size=config.size, frames=args.frames)
    system = SlamSystem(config, sequence.intrinsics, total_frames=len(sequence))
    worst_ratio, worst_frame = 0.0, -1
    relocalised, truth, stopped = [], [], None
    for i in range(len(sequence)):
        frame = sequence.frame(i)
        level = system.track_level.level()
        try:
            result = system.process(frame)
        except TrackingLostError as lost:
            stopped = {"frame": lost.frame, "timestamp": lost.timestamp, "reason": lost.reason}
            break
        truth.append(frame.T_world_cam)
        tracking = result.tracking
        if tracking is None:
            continue
        ratio = tracking.depth / level if level else float("nan")
        if np.isfinite(ratio) and ratio > worst_ratio:
            worst_ratio, worst_frame = ratio, frame.index
        if tracking.relocalised:
            relocalised.append(frame.index)
        if args.per_frame:
            record = {"frame": frame.index, "depth_error": tracking.depth, "ratio": ratio}
            print(
                json.dumps(
                    {k: round(v, 4) if isinstance(v, float) else v for k, v in record.items()}
                )
            )
    ate = None
    if len(truth) >= 2 and all(T is not None for T in truth):
        ate = ate_rmse_cm(np.array(truth), np.array(system.refined_poses()[: len(truth)]))
    summary = {
        "sequence": args.seq,
        "frames": args.frames,
        "tracked": len(system.poses),
        "largest_ratio": {"ratio": round(worst_ratio, 3), "frame": worst_frame},
        "relocalised": relocalised,
        "stopped": stopped,
        "ate_rmse_cm": None if ate is None else round(ate, 3),
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
