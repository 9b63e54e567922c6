"""A receiver-aware share (`gsc share A.mcap OUT --for B.mcap`): send first what B has not seen.

A per-Gaussian score ranks A's map by what it drew for A; it cannot know that B already holds half
of it. The receiver can say so cheaply: its estimated camera poses and its calibration (`Request`:
at most `MAX_REQUEST_VIEWS` poses spread over its run, 28 bytes each packed as float32,
`pack_request`). The sender renders its own map from those poses, without optimising anything, and
sums each Gaussian's alpha x T over them (the alpha*T sum of `gscompress.ops.score.score_map`): the
pixels of B's views the Gaussian draws, with A's geometry for the occlusion. A Gaussian that draws
less than `SEEN_PIXELS` there lies where B has not looked; the share sends those first, in the
strategy's order, then the others in that order (`gscompress.selection.top_k_first`).

The request's bytes count in a byte budget: the share file and the request together fit in it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.camera import Intrinsics, rotmat_to_quat
from gscompress.errors import BudgetError, InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.mcap_log import TOPIC_POSE, LogReader
from gscompress.ops.budget import Budget
from gscompress.pipeline.logs import trajectory

MAX_REQUEST_VIEWS = 64
"""The most of the receiver's poses a request holds (spread evenly over its run)."""

SEEN_PIXELS = 1.0
"""A Gaussian drawing less than this many pixels (alpha x T summed over the receiver's views)
counts as unseen by the receiver."""


@dataclass(frozen=True)
class Request:
    """What the receiver tells the sender: where its camera has been.

    Attributes:
        poses: [M, 4, 4] camera-to-world poses, in the receiver's world frame.
        intrinsics: the receiver's camera (its working size).
        world_frame: the receiver's world frame (`LogMetadata.world_frame`).
        data: the request as the receiver sends it (`pack_request`; its length is what a
            byte budget counts).
        source: the file it was read from.
    """

    poses: np.ndarray
    intrinsics: Intrinsics
    world_frame: str
    data: bytes
    source: str

    def record(self) -> dict[str, Any]:
        """What a share records of the request it was cut for."""
        return {
            "for": Path(self.source).name,
            "views": len(self.poses),
            "request_bytes": len(self.data),
        }


def read_request(path: str | Path) -> Request:
    """The request of the agent whose log is `path`: its estimated poses (at most
    `MAX_REQUEST_VIEWS`, spread evenly) and calibration, and their bytes (`pack_request`).

    Raises:
        InputError: the log has no estimated poses or no calibration.
    """
    with LogReader(path) as log:
        poses = trajectory(log).T_world_cam
        intrinsics = log.read_intrinsics()
        world_frame = log.metadata.world_frame
    if not len(poses):
        raise InputError(f"{path} has no {TOPIC_POSE}: it cannot say where its camera has been")
    if intrinsics is None:
        raise InputError(f"{path} has no camera calibration: the views cannot be rendered")
    pick = np.unique(np.linspace(0, len(poses) - 1, min(len(poses), MAX_REQUEST_VIEWS)).round())
    poses = poses[pick.astype(np.int64)]
    return Request(poses, intrinsics, world_frame, pack_request(poses, intrinsics), str(path))


def pack_request(poses: np.ndarray, intrinsics: Intrinsics) -> bytes:
    """The request as the receiver sends it: float32 little-endian, the camera (fx, fy, cx, cy,
    width, height), then per pose its translation (3) and unit quaternion (w, x, y, z): 24 bytes
    and 28 per pose (its length is what a byte budget counts)."""
    camera = [
        intrinsics.fx,
        intrinsics.fy,
        intrinsics.cx,
        intrinsics.cy,
        intrinsics.width,
        intrinsics.height,
    ]
    rows = [np.r_[T[:3, 3], rotmat_to_quat(T[:3, :3])] for T in poses]
    return np.concatenate([camera, *rows]).astype("<f4").tobytes()


def unseen_ids(
    gaussians: GaussianMap,
    request: Request,
    T_request_map: np.ndarray | None = None,
    *,
    backend: str = "auto",
    device: str = "auto",
) -> np.ndarray:
    """Ids of the Gaussians of `gaussians` that draw less than `SEEN_PIXELS` pixels in the
    request's views, rendered with the map's own geometry.

    Args:
        T_request_map: the transform from the map's world frame to the request's (None: the
            same frame).
    """
    from gscompress.ops.score import score_map
    from gscompress.render import resolve_device

    poses = request.poses
    if T_request_map is not None:
        poses = np.linalg.inv(T_request_map) @ poses
    seen = score_map(
        gaussians,
        poses,
        request.intrinsics,
        sigma_d=math.inf,
        backend=backend,
        device=resolve_device(device, backend),
    ).alpha_t_sum
    return gaussians.ids[seen < SEEN_PIXELS]


def budget_less_request(budget: Budget, request: Request) -> Budget:
    """A byte budget less the request's bytes (what is left for the share file); a fraction
    budget as it is.

    Raises:
        BudgetError: the request alone takes the whole budget.
    """
    if budget.budget_bytes is None:
        return budget
    left = budget.budget_bytes - len(request.data)
    if left < 1:
        raise BudgetError(
            f"the receiver's request ({len(request.data)} B) takes the whole budget {budget}"
        )
    return Budget(budget_bytes=left, fp32_fraction=budget.fp32_fraction, text=str(budget))
