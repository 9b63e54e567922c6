"""Cross-agent scoring: one map scored on agent A's frames, on agent B's frames and on all the
experiment's frames, each frame's pose refined against the fixed map (`gsc eval
--refine-poses`, `gscompress.pipeline.evaluate.evaluate_log`).

Each agent's map is consistent with its own estimated trajectory, and two agents anchored at
the ground truth still sit centimetres apart: scored at the other agent's poses, that offset,
not the map, would decide the figures. So every frame starts at an estimated pose and is moved
to where the fixed map explains it best, and the scores are taken there. Starting poses:

- on the frames of the agent that made the map (A for A's map; B for B's, for B with a share
  and for B refined without one): that agent's own estimated poses (those of the map's log);
- on the other agent's frames: the other agent's estimated poses (its log's, as `gsc eval
  --poses-from`), with anchor "own" first moved into the map's world frame by the estimated
  transform of the experiment's alignment step (A's world to B's; its inverse for A's map);
- on all frames: the map's own poses where its log has them, the other agent's (moved) on the
  rest. The centralised run (one agent on every frame) starts at its own poses everywhere.

A pose is refined frame by frame, so the figures on all frames are not computed again: they
are those of A's frames and B's together, each frame once, from the set whose starting pose
the all-frame set gives it (the map's own agent's set; either for the centralised run). With
`every` > 1 the all-frame set is therefore the frames scored on A's and B's.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.files import json_text, write_text_atomic

log = logging.getLogger(__name__)


FRAME_SETS = ("a", "b", "all")
"""The frame sets a map is scored on: agent A's frames, agent B's, all the experiment's."""


SUMMARY_KEYS = ("frames_evaluated", "psnr", "ssim", "lpips", "depth_l1_cm")
"""What a scoring step's record keeps of each frame set's evaluation at the starting poses,
beside the set's `frames`, where its poses `start` and `refined` (the same at the refined poses,
with the median pose change)."""


def start_poses(
    own_log: Path, other_log: Path, T_own_other: np.ndarray | None, own_first: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The starting poses of a frame set that holds the other agent's frames.

    Args:
        own_log: the scored map's log (its estimated poses).
        other_log: the other agent's log.
        T_own_other: [4, 4] the other agent's world frame to the map's (None: they share one).
        own_first: keep the map's own poses wherever it has one (all frames), else the other
            agent's poses alone (the other agent's frames).

    Returns:
        (times [N] int64 ns, camera-to-world poses [N, 4, 4]) in time order.
    """
    from gscompress.io.trajectory import nearest_times
    from gscompress.pipeline.logs import POSE_MATCH_TOLERANCE_NS, pose_source

    times, poses, _, _ = pose_source(other_log)
    if T_own_other is not None:
        poses = T_own_other @ poses
    if own_first:
        own_times, own_poses, _, _ = pose_source(own_log)
        rest = nearest_times(times, own_times, POSE_MATCH_TOLERANCE_NS) < 0
        times = np.concatenate([own_times, times[rest]])
        poses = np.concatenate([own_poses, poses[rest]])
        order = np.argsort(times, kind="stable")
        times, poses = times[order], poses[order]
    return times, poses


def cross_scores(
    path: Path,
    seq: Path,
    log_path: Path,
    own: str,
    frames: dict[str, str],
    other: Path | None,
    transform: Path | None,
    iters: int,
    every: int,
    lpips: bool,
    device: str,
) -> dict[str, Any]:
    """Score the map of `log_path` on each of `FRAME_SETS` at refined poses.

    Args:
        path: the JSON file written with each set's full evaluation (per frame too); the
            starting poses that are not one log's own are written beside it as TUM
            trajectories (`<stem>_start_<set>.txt`, what `gsc eval --poses` reads).
        seq: the sequence folder.
        log_path: the map's log.
        own: the frame set of the agent that made the map: "a", "b", or "all" (the
            centralised run, which has a pose for every frame).
        frames: each set's frame subset (`gsc eval --frames`).
        other: the other agent's log (None when `own` is "all").
        transform: with anchor "own", the alignment's estimate of A's world frame to B's
            (`gsc align`'s file, `T_target_source`); None: the agents share a world frame.
        iters: tracking iterations of the refinement.
        every: score every N-th frame of each set.
        lpips: compute LPIPS.
        device: torch device.

    Returns:
        `cross`: per set, its `frames`, where its poses `start`, its `SUMMARY_KEYS` at the
        starting poses and `refined` (iterations, PSNR, SSIM, LPIPS, depth L1 and the median
        pose change in cm and degrees, without the per-frame list).
    """
    from gscompress.io.trajectory import read_transform, write_tum_trajectory
    from gscompress.pipeline.evaluate import evaluate_log, union_results
    from gscompress.pipeline.images import ImageOptions

    T_own_other = None
    if transform is not None and own != "all":
        T_b_a = read_transform(transform)
        T_own_other = T_b_a if own == "b" else np.linalg.inv(T_b_a)
    base = path.name.split(".")[0]
    full: dict[str, Any] = {}
    summary: dict[str, Any] = {}
    for name in FRAME_SETS:
        poses: dict[str, Any] = {}
        start = "own"
        if own not in ("all", name):
            assert other is not None
            own_first = name == "all"
            start = "own, the other agent's elsewhere" if own_first else "the other agent's"
            if T_own_other is None and not own_first:
                poses["poses_from"] = other
            else:
                times, T = start_poses(log_path, other, T_own_other, own_first)
                tum = path.with_name(f"{base}_start_{name}.txt")
                write_tum_trajectory(
                    tum,
                    times / 1e9,
                    T,
                    [f"starting poses of {log_path.name} on {name} frames: {start}"],
                )
                poses["poses"] = tum
        if name == "all":  # A's frames and B's hold every frame, each from its starting pose
            first, second = ("a", "b") if own == "all" else (own, "b" if own == "a" else "a")
            result = union_results(full[first], full[second])
        else:
            views = ImageOptions(
                frames=frames[name], every=every, lpips=lpips, device=device, **poses
            )
            result = evaluate_log(log_path, seq, views, refine_poses=iters)
        full[name] = result
        refined = {k: v for k, v in result["refined"].items() if k != "per_frame"}
        summary[name] = {
            "frames": frames[name],
            "start": start,
            "refined": refined,
            **{key: result.get(key) for key in SUMMARY_KEYS},
        }
        log.debug(
            "%s on %s frames: PSNR %.2f at refined poses (%.2f at the start)",
            log_path.name,
            name,
            refined["psnr"] or float("nan"),
            result["psnr"] or float("nan"),
        )
    write_text_atomic(path, json_text(full, indent=1))
    return {"cross": summary}
