"""How far each agent's own trajectory drifts from the ground truth, from its first frame on.

For each log (made with its ground-truth poses recorded, e.g. `gsc slam` on a sequence with
them), the estimated poses (the refined trajectory where the log has one, else the tracked poses;
`--tracked` for those) are paired with the true ones by time, and the estimated motion from
the first paired pose to the k-th (k counts the log's poses, not the sequence's frames: with
`--frames 0:30:2`, k = 10 is frame 20) is compared with the true one: the error of that
relative pose (translation cm, rotation degrees, `ops.align.transform_error`) and the ratio of
the estimated rotation angle and distance to the true ones (below 1: the agent turned or moved
less than the camera did; null where the camera turned less than 0.1 degree or moved less than
1 mm, which no ratio describes). Also the ratio of the path lengths, pose to pose. An
own-anchored alignment can come no closer to the truth than this drift over the frames the two
agents share (docs/align.md). Prints one JSON object per log.

    python bench/drift.py A.mcap B.mcap --at 10,20,25
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from gscompress.camera import invert_transform, rotation_angle_deg
from gscompress.io.mcap_log import TOPIC_POSE, TOPIC_POSE_GT, LogReader
from gscompress.io.trajectory import nearest_times
from gscompress.ops.align import transform_error
from gscompress.pipeline.logs import POSE_MATCH_TOLERANCE_NS

MIN_TURN_DEG, MIN_MOVE_M = 0.1, 1e-3


def relative(poses: np.ndarray, k: int) -> np.ndarray:
    """Camera k's pose in camera 0's frame."""
    return invert_transform(poses[0]) @ poses[k]


def path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def ratio(value: float, truth: float, least: float) -> float | None:
    return value / truth if truth >= least else None


def drift(path: str, at: list[int], tracked: bool = False) -> dict[str, object]:
    with LogReader(path) as log:
        trajectory = log.read_trajectory()
        t_est, est = (
            log.read_poses(TOPIC_POSE) if tracked else (trajectory.times_ns, trajectory.T_world_cam)
        )
        t_gt, gt = log.read_poses(TOPIC_POSE_GT)
    poses = "tracked" if tracked else trajectory.source
    pair = nearest_times(t_est, t_gt, POSE_MATCH_TOLERANCE_NS)
    est, gt = est[pair >= 0], gt[pair[pair >= 0]]
    if len(est) < 2:
        return {"log": path, "error": f"{len(est)} estimated poses with a true one; need 2"}
    rows = []
    for k in [k for k in at if 0 < k < len(est)] or [len(est) - 1]:
        e, g = relative(est, k), relative(gt, k)
        cm, deg = transform_error(e, g)
        turned, true_turn = rotation_angle_deg(e[:3, :3]), rotation_angle_deg(g[:3, :3])
        moved, true_move = float(np.linalg.norm(e[:3, 3])), float(np.linalg.norm(g[:3, 3]))
        rows.append(
            {
                "pose": k,
                "error_cm": 100 * cm,
                "error_deg": deg,
                "turn_ratio": ratio(turned, true_turn, MIN_TURN_DEG),
                "move_ratio": ratio(moved, true_move, MIN_MOVE_M),
            }
        )
    return {
        "log": path,
        "trajectory": poses,
        "poses": len(est),
        "at": rows,
        "path_ratio": ratio(path_length(est), path_length(gt), MIN_MOVE_M),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("logs", nargs="+")
    parser.add_argument(
        "--at",
        default="10,20,25",
        help="the k-th poses of each log to compare at (those past its end are left out; "
        "none left: its last)",
    )
    parser.add_argument(
        "--tracked", action="store_true", help="the poses as tracked, not the refined trajectory"
    )
    args = parser.parse_args()
    at = [int(x) for x in args.at.split(",") if x.strip()]
    for path in args.logs:
        print(json.dumps(drift(path, at, args.tracked)))


if __name__ == "__main__":
    main()
