"""`gsc export-traj`: a log's estimated (or ground-truth) poses as a TUM trajectory, for evo and
other tools (numpy + mcap only, never torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gscompress.errors import LogFormatError
from gscompress.io.files import check_output
from gscompress.io.mcap_log import TOPIC_POSE, TOPIC_POSE_GT, LogReader
from gscompress.io.trajectory import write_tum_trajectory
from gscompress.pipeline.logs import trajectory


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
        if ground_truth:
            stamps_ns, poses = log_in.read_poses(topic)
            source = "ground truth"
        else:
            found = trajectory(log_in)
            stamps_ns, poses, source = found.times_ns, found.T_world_cam, found.source
    if len(poses) == 0:
        what = "ground-truth poses" if ground_truth else "estimated poses (not a SLAM log?)"
        raise LogFormatError(f"{src} has no {topic} messages: no {what}")
    refined = "" if source in ("tracked", "ground truth") else f" ({source})"
    name = "ground truth" if ground_truth else f"estimated trajectory{refined}"
    write_tum_trajectory(dst, stamps_ns / 1e9, poses, [f"{name} of {Path(src).name}"])
    return {"output": str(dst), "poses": len(poses), "topic": topic, "trajectory": source}
