"""How far each agent's own trajectory drifts from the ground truth, from its first frame on.

For each log (made with its ground-truth poses recorded, e.g. `gsc slam` on a sequence with
them), the estimated motion from the first frame to frame k is compared with the true one:
the error of that relative pose (translation cm, rotation degrees, `ops.align.transform_error`)
and the ratio of the estimated rotation angle and distance to the true ones (below 1: the
agent turned or moved less than the camera did). Also the ratio of the path lengths, frame to
frame. An own-anchored alignment can come no closer to the truth than this drift over the
frames the two agents share (docs/align.md). Prints one JSON object per log.

    python bench/drift.py A.mcap B.mcap --at 10,20,25
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from gscompress.camera import invert_transform, rotation_angle_deg
from gscompress.io.mcap_log import TOPIC_POSE, TOPIC_POSE_GT, LogReader
from gscompress.ops.align import transform_error


def relative(poses: np.ndarray, k: int) -> np.ndarray:
    """Camera k's pose in camera 0's frame."""
    return invert_transform(poses[0]) @ poses[k]


def path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def drift(path: str, at: list[int]) -> dict[str, object]:
    with LogReader(path) as log:
        _, est = log.read_poses(TOPIC_POSE)
        _, gt = log.read_poses(TOPIC_POSE_GT)
    if len(est) != len(gt) or len(est) < 2:
        return {"log": path, "error": f"{len(est)} estimated and {len(gt)} true poses"}
    rows = []
    for k in [k for k in at if 0 < k < len(est)] or [len(est) - 1]:
        e, g = relative(est, k), relative(gt, k)
        cm, deg = transform_error(e, g)
        turned, true_turn = rotation_angle_deg(e[:3, :3]), rotation_angle_deg(g[:3, :3])
        moved, true_move = float(np.linalg.norm(e[:3, 3])), float(np.linalg.norm(g[:3, 3]))
        rows.append({
            "frame": k, "error_cm": 100 * cm, "error_deg": deg,
            "turn_ratio": turned / max(true_turn, 1e-9),
            "move_ratio": moved / max(true_move, 1e-12),
        })  # fmt: skip
    return {"log": path, "frames": len(est), "at": rows,
            "path_ratio": path_length(est) / max(path_length(gt), 1e-12)}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("logs", nargs="+")
    parser.add_argument("--at", default="10,20,25", help="frames (of each log) to compare at")
    args = parser.parse_args()
    at = [int(x) for x in args.at.split(",") if x.strip()]
    for path in args.logs:
        print(json.dumps(drift(path, at)))


if __name__ == "__main__":
    main()
