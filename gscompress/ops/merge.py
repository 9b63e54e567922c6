"""Merging another agent's share into a map, and refining the result.

`merge_maps` is exact: every Gaussian of both maps, with all its parameters and PWAS sums, is
in the result. Ids stay as they are unless the two maps share some; then the share's ids are
all moved by one offset past the receiver's largest id, so `id - offset` still names the
Gaussian in the sending agent's map.

The merged map is then refined on the receiver's own views by `gscompress.ops.refine.refine`
(a merge never drops a Gaussian).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gscompress.camera import quat_to_rotmat, rotmat_to_quat
from gscompress.errors import MapError
from gscompress.gaussians import GaussianMap

MAX_ID = np.iinfo(np.uint32).max


def check_same_world(receiver: str, share: str, what: str) -> None:
    """Refuse to combine maps whose world frames are unknown or not known to agree."""
    if not receiver or not share:
        raise MapError(
            f"{what}: the world frame of {'the share' if not share else 'the receiver'} is "
            "unknown; only maps anchored to the same frame can be combined (give the transform "
            "between the two frames with --share-transform)"
        )
    if receiver != share:
        raise MapError(
            f"{what}: the share is expressed in {share!r} but the receiver in {receiver!r}; "
            "maps whose world frames are not known to agree cannot be combined (give the "
            "transform between them with --share-transform)"
        )


def transform_map(gaussians: GaussianMap, T_new_old: np.ndarray) -> GaussianMap:
    """The map expressed in another frame: means and orientations moved by a rigid transform.

    Args:
        gaussians: the map (SH degree 0: higher bands would need rotating too).
        T_new_old: [4, 4] rigid transform taking points of the map's frame to the new frame.

    Raises:
        MapError: not a rigid transform, one that moves Gaussians beyond float32 range, or a
            map with higher SH bands.
    """
    T = np.asarray(T_new_old, dtype=np.float64)
    R = T[:3, :3]
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(
        R @ R.T, np.eye(3), atol=1e-6
    ) or not np.isclose(np.linalg.det(R), 1.0, atol=1e-6):  # fmt: skip
        raise MapError("the transform is not a finite rigid 4x4 transform (rotation + shift)")
    if gaussians.sh_degree > 0:
        raise MapError("moving a map with SH degree > 0 needs its SH rotated; not supported")
    if len(gaussians) == 0:
        return gaussians
    with np.errstate(over="ignore"):
        means = (gaussians.means.astype(np.float64) @ R.T + T[:3, 3]).astype(np.float32)
    if not np.all(np.isfinite(means)):
        raise MapError("the transform moves Gaussians beyond the float32 range of a map")
    quats = rotmat_to_quat(R @ quat_to_rotmat(gaussians.quats))
    return replace(gaussians, means=means, quats=quats.astype(np.float32))


def merge_maps(receiver: GaussianMap, share: GaussianMap) -> tuple[GaussianMap, int]:
    """Concatenate `share` after `receiver`.

    Returns:
        The merged map (receiver rows first, then the share's) and the offset added to the
        share's ids (0 when no id clashed).

    Raises:
        MapError: SH degrees differ, or shifted ids would not fit in uint32.
    """
    offset = 0
    if len(receiver) and len(share) and np.intersect1d(receiver.ids, share.ids).size:
        offset = int(receiver.ids.max()) + 1 - int(share.ids.min())
        if int(share.ids.max()) + offset > MAX_ID:
            raise MapError("the share's ids cannot be moved past the receiver's within uint32")
        share = replace(share, ids=(share.ids.astype(np.int64) + offset).astype(np.uint32))
    return GaussianMap.concat([receiver, share]), offset
