"""Merging another agent's share into a map, and refining the result.

`merge_maps` is exact: every Gaussian of both maps, with all its parameters and PWAS sums, is
in the result. Ids stay as they are unless the two maps share some; then the share's ids are
all moved by one offset past the receiver's largest id, so `id - offset` still names the
Gaussian in the sending agent's map.

`refine` then optimises the merged map on the receiver's own views (poses fixed) with a fresh
optimizer, as the SLAM mapper does (`gscompress.slam.mapper`), but without the cyclic removal
(a merge never drops a Gaussian) and with learning rates that may decay over the refinement.
PWAS sums are carried, not added to.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from gscompress.camera import Intrinsics, quat_to_rotmat, rotmat_to_quat
from gscompress.errors import DivergenceError, MapError
from gscompress.gaussians import GaussianMap
from gscompress.seeds import seeded_rng

REFINE_VIEWS = ("frames", "keyframes")
"""What a refinement runs on: every frame of a run, or its keyframes (every `keyframes.every`-th;
the SLAM's own final refinement adds the last frame)."""

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


def refine(
    gaussians: GaussianMap,
    views: Sequence[Any],
    intrinsics: Intrinsics,
    config: Any,
    iters: int,
    *,
    device: Any = "cpu",
    seed: int = 0,
    lr_final_fraction: float = 1.0,
    progress: Callable[[int], object] | None = None,
) -> tuple[GaussianMap, dict[str, Any]]:
    """Optimise a map on fixed views for `iters` iterations, each view once per shuffled pass.

    Args:
        gaussians: the map (SH degree 0: the SLAM parameterisation).
        views: `gscompress.slam.keyframes.View` objects (observed colour, depth and pose).
        intrinsics: camera intrinsics at the views' size.
        config: a `SlamConfig` (mapping loss and learning rates are taken from it).
        iters: iterations.
        device: torch device of the views.
        seed: seed of the view order.
        lr_final_fraction: the learning rates (the config's mapping ones) decay geometrically
            to this fraction of their value at the last iteration (1: constant).
        progress: called with 1 after each iteration.

    Returns:
        The refined map (same Gaussians, same order, same ids and sums) and
        {"iters", "loss_before", "loss_after"}: the mean mapping loss over all the views
        before and after the refinement.

    Raises:
        MapError: a map with higher SH bands (they would be dropped), or no views.
        InputError: a negative seed.
        DivergenceError: the refinement's loss or the map stopped being finite.
    """
    import torch

    from gscompress.slam.mapper import Mapper

    rng = seeded_rng(seed)
    if iters <= 0 or len(gaussians) == 0:
        return gaussians, {"iters": 0}
    if gaussians.sh_degree > 0:
        raise MapError(
            f"refinement optimises SH degree 0 only; this map has degree {gaussians.sh_degree} "
            "(merge with 0 iterations to keep its higher bands)"
        )
    if not views:
        raise MapError("no views to refine on")
    config = config.with_overrides(**{"prune.opacity_every": 0, "isotropic": gaussians.isotropic})
    mapper = Mapper(config, intrinsics, torch.device(device))
    mapper.add(gaussians)
    views = list(views)
    loss_before = mapper.loss(views)
    on_step = None if progress is None else lambda _: progress(1)
    try:
        mapper.refine(views, iters, rng, on_step=on_step, lr_final_fraction=lr_final_fraction)
    except DivergenceError as exc:  # (its rates are the receiver's mapping ones, from its log)
        raise DivergenceError(
            "the refinement",
            exc.detail,
            "it ran at the receiver's mapping rates; merge with --iters 0 to concatenate only",
        ) from None
    stats = {"iters": iters, "loss_before": loss_before, "loss_after": mapper.loss(views)}
    return mapper.params.to_map(), stats
