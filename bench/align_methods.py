"""The merge's alignment by each ICP of the local step, on the same pair of agents: the
transform it finds, and the merged map's PSNR on both agents' frames.

A and B are two agents' logs of one sequence anchored in one world frame (at the ground-truth
pose of their first frame, as `gsc slam` anchors by default; the halves protocol's agents).
In one call, for each ICP (`gscompress.ops.icp.ICP`: builtin, and open3d where Open3D loads;
with `--small-gicp`, small_gicp's GICP as a candidate registered here, `pip install small_gicp`):

1. A's share, cut once by `gsc share A.mcap S.mcap --budget BUDGET` (or A's whole map with
   `--budget 1`), is merged into B with `gsc merge`'s defaults and that ICP
   (`merge_logs(..., merge={"icp": NAME})`, `--iters` refinement iterations).
2. The alignment the merge applied (`align_transform`, the identity where it was not kept), and
   its error against the truth: the identity, both agents being in the ground truth's frame
   (so the error is how far the alignment moved the share; the agents' own drift is in it).
3. The merged map scored on B's frames at B's poses, and on A's frames at A's estimated poses
   refined against the merged map (`--refine-poses`, as `gsc experiment` scores across
   agents), every `--every`-th frame, without LPIPS.
4. `gsc align`'s local step alone on the two whole maps (`refine_alignment` from the identity,
   as `gsc align --init I.txt`): its transform and error.

Differences are given against the first method (builtin). Prints one JSON object and writes it
to OUT/result.json; the runs are kept under OUT.

    python bench/align_methods.py A.mcap B.mcap --seq SEQ --out OUT [--budget 5%bytes]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.files import json_text
from gscompress.io.mcap_log import LogReader
from gscompress.ops.align import AlignOptions, refine_alignment, transform_error
from gscompress.ops.icp import ICP, Cloud, Stages
from gscompress.pipeline.aligning import log_cloud
from gscompress.pipeline.evaluate import evaluate_log
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.merge import merge_logs
from gscompress.threads import use_threads


def icp_small_gicp(
    source: Cloud, target: Cloud, T: np.ndarray, voxel: float, stages: Stages, colored: bool
) -> np.ndarray:
    """small_gicp's GICP (geometry only: it has no colour term) with the local step's stages,
    on the same grids; a candidate, registered in `ICP` by this script only."""
    import small_gicp

    src, tgt = small_gicp.PointCloud(source.points), small_gicp.PointCloud(target.points)
    for cloud in (src, tgt):
        small_gicp.estimate_covariances(cloud, num_neighbors=20)
    tree = small_gicp.KdTree(tgt)
    for scale, iters in stages:
        result = small_gicp.align(
            tgt,
            src,
            tree,
            init_T_target_source=T,
            registration_type="GICP",
            max_correspondence_distance=scale * voxel,
            max_iterations=iters,
            rotation_epsilon=1e-6,
            translation_epsilon=1e-6,
        )
        T = np.asarray(result.T_target_source)
    return T


def methods(small_gicp: bool) -> list[str]:
    """The ICPs this machine can run, builtin first."""
    names = ["builtin"]
    try:
        import open3d  # noqa: F401

        names.append("open3d")
    except ImportError:
        pass
    if small_gicp:
        ICP["small_gicp"] = icp_small_gicp
        names.append("small_gicp")
    return names


def frames_of(path: Path) -> str:
    with LogReader(path) as log:
        return log.metadata.frames


def world_of(path: Path) -> str:
    with LogReader(path) as log:
        return log.metadata.world_frame


def error(T: np.ndarray) -> dict[str, float]:
    """`T`'s error against the identity (cm, degrees)."""
    dt, dr = transform_error(np.asarray(T, np.float64), np.eye(4))
    return {"error_cm": 100.0 * dt, "error_deg": dr}


def scores(result: dict[str, Any]) -> dict[str, Any]:
    keep = ("psnr", "ssim", "depth_l1_cm", "frames_evaluated")
    out = {k: result[k] for k in keep if k in result}
    if "refined" in result:
        out["refined"] = {k: result["refined"].get(k) for k in ("psnr", "ssim")}
    return out


def cut_share(a: Path, share: Path, budget: str) -> None:
    """A's share as `gsc share` cuts it by default."""
    command = [
        sys.executable,
        "-m",
        "gscompress_cli",
        "--threads",
        "1",
        "share",
        str(a),
        str(share),
        "--budget",
        budget,
        "--force",
    ]
    subprocess.run(command, check=True, capture_output=True, text=True)


def run_method(
    name: str, args: argparse.Namespace, share: Path, clouds: tuple[Cloud, Cloud]
) -> dict[str, Any]:
    """Merge the share into B with the ICP `name`, score the result, and align the two whole
    maps by the local step alone."""
    merged = args.out / f"merged_{name}.mcap"
    done = merge_logs(
        args.b, share, merged, seq=args.seq, iters=args.iters, merge={"icp": name}, force=True
    )
    T = np.asarray(done.get("align_transform", np.eye(4)), np.float64)
    on_b = evaluate_log(merged, args.seq, ImageOptions(every=args.every, lpips=False))
    on_a = evaluate_log(
        merged,
        args.seq,
        ImageOptions(frames=frames_of(args.a), every=args.every, poses_from=args.a, lpips=False),
        refine_poses=args.refine_poses,
    )
    local = refine_alignment(*clouds, np.eye(4), AlignOptions(icp=name)).T_target_source
    return {
        "merge": {k: v for k, v in done.items() if k.startswith("align_")} | error(T),
        "T": T.tolist(),
        "b_frames": scores(on_b),
        "a_frames": scores(on_a),
        "local_step": {"T": local.tolist()} | error(local),
    }


def differences(method: dict[str, Any], first: dict[str, Any]) -> dict[str, float]:
    """`method`'s transforms and PSNRs against `first`'s."""
    dt, dr = transform_error(np.asarray(method["T"]), np.asarray(first["T"]))
    lt, lr = transform_error(
        np.asarray(method["local_step"]["T"]), np.asarray(first["local_step"]["T"])
    )
    a, a0 = method["a_frames"], first["a_frames"]
    return {
        "merge_transform_cm": 100.0 * dt,
        "merge_transform_deg": dr,
        "local_step_cm": 100.0 * lt,
        "local_step_deg": lr,
        "psnr_b_frames": method["b_frames"]["psnr"] - first["b_frames"]["psnr"],
        "psnr_a_frames": a["psnr"] - a0["psnr"],
        "psnr_a_frames_refined": a["refined"]["psnr"] - a0["refined"]["psnr"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    parser.add_argument("--seq", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--budget", default="5%bytes", help="A's share (1: A's whole map)")
    parser.add_argument("--iters", type=int, default=200)
    parser.add_argument("--every", type=int, default=2)
    parser.add_argument("--refine-poses", type=int, default=100)
    parser.add_argument("--small-gicp", action="store_true", help="small_gicp's GICP too")
    args = parser.parse_args()
    use_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    if world_of(args.a) != world_of(args.b):
        raise SystemExit(f"{args.a} and {args.b} are not in one world frame")
    names = methods(args.small_gicp)
    share = args.out / "share.mcap"
    cut_share(args.a, share, args.budget)
    clouds = (log_cloud(args.a)[0], log_cloud(args.b)[0])
    results = {name: run_method(name, args, share, clouds) for name in names}
    for name in names[1:]:
        results[name][f"minus_{names[0]}"] = differences(results[name], results[names[0]])
    record = {
        "a": str(args.a),
        "b": str(args.b),
        "seq": str(args.seq),
        "budget": args.budget,
        "iters": args.iters,
        "methods": results,
    }
    text = json_text(record, indent=2)
    (args.out / "result.json").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
