"""Two agents that never shared a frame: `gsc align`'s transform against the true one, and B
with A's share merged at each.

A and B are logs of one sequence, each agent at the identity at its own first frame (`gsc
slam --config` with `init_from_ground_truth: false`, e.g. the halves of `--split halves`). The
true transform (A's world -> B's) comes from their ground-truth first-frame poses. Steps, all
written under --out:
1. `align_agents(A, B)`: the estimated transform, its error against the true one (cm,
   degrees); beside it, the offset that local refinement alone finds from the true transform
   (the agents' own drift: how far apart their maps sit even when placed exactly). A refused
   alignment is reported as such and its estimate still merged (a miss).
2. A's share (`--budget`, pwas), merged into B at the estimated and at the true transform,
   `--iters` refinement iterations (0 by default) and without the merge's own local
   re-alignment (`MergeOptions(align=False)`): the difference is the transform's alone.
3. Each merged log scored on B's own frames at B's poses, and on every `--every`-th frame of the
   sequence at its ground-truth pose expressed in B's frame (A's part included).

Prints one JSON object (and writes it to OUT/result.json).

    python bench/align_agents.py A.mcap B.mcap --seq SEQ --out OUT
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.files import json_text
from gscompress.io.mcap_log import TOPIC_POSE_GT, LogReader
from gscompress.io.trajectory import write_tum_trajectory
from gscompress.ops.merge import MergeOptions
from gscompress.pipeline.align import align_agents
from gscompress.pipeline.evaluate import evaluate_log
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.merge import merge_logs
from gscompress.pipeline.share import share_log


def ground_truth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with LogReader(path) as log:
        return log.read_poses(TOPIC_POSE_GT)


def scores(result: dict[str, Any]) -> dict[str, Any]:
    keep = ("psnr", "ssim", "depth_l1_cm", "gaussians", "frames_evaluated")
    return {k: result.get(k) for k in keep}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    parser.add_argument("--seq", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--budget", default="0.2")
    parser.add_argument("--iters", type=int, default=0)
    parser.add_argument("--every", type=int, default=2)
    parser.add_argument(
        "--on-frames",
        action="store_true",
        help="refine the registration on B's frames (gsc align --seq)",
    )
    args = parser.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)

    t_a, gt_a = ground_truth(args.a)
    t_b, gt_b = ground_truth(args.b)
    record: dict[str, Any] = {"a": str(args.a), "b": str(args.b), "seq": str(args.seq)}
    record["align"] = align_agents(
        args.a,
        args.b,
        out / "T_est.txt",
        out / "T_true.txt",
        seq=args.seq if args.on_frames else None,
    )
    record["align"].pop("hypotheses", None)
    share = out / "a_share.mcap"
    share_log(args.a, share, args.budget, force=True)
    times = np.concatenate([t_a, t_b])
    order = np.argsort(times)
    times, first = np.unique(times[order], return_index=True)
    poses = np.concatenate([gt_a, gt_b])[order][first]
    gt_in_b = out / "gt_in_b.txt"
    T_b_gt = np.linalg.inv(gt_b[0])
    write_tum_trajectory(gt_in_b, times / 1e9, T_b_gt @ poses, ["ground truth in B's frame"])
    for name, transform in (("est", out / "T_est.txt"), ("true", out / "T_true.txt")):
        merged = out / f"b_merged_{name}.mcap"
        merge_logs(
            args.b,
            share,
            merged,
            seq=args.seq,
            iters=args.iters,
            share_transform=transform,
            merge=MergeOptions(align=False),
            force=True,
        )
        own = evaluate_log(merged, args.seq, ImageOptions(lpips=False))
        views = ImageOptions(frames="all", poses=gt_in_b, every=args.every, lpips=False)
        every = evaluate_log(merged, args.seq, views)
        record[f"merge_{name}"] = {"b_frames": scores(own), "all_frames_gt": scores(every)}
    b_alone = evaluate_log(args.b, args.seq, ImageOptions(lpips=False))
    record["b_alone"] = {"b_frames": scores(b_alone)}
    for view in ("b_frames", "all_frames_gt"):
        est, true = record["merge_est"][view]["psnr"], record["merge_true"][view]["psnr"]
        record[f"psnr_est_minus_true_{view}"] = est - true
    text = json_text(record, indent=2)
    (out / "result.json").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
