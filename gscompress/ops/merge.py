"""Merging another agent's share into a map, and refining the result.

`combine` is the merge (`MergeOptions`): the share is moved onto the receiver where their
surfaces overlap (`align_share`, a local rigid refinement: two agents anchored in one frame
still sit centimetres apart), the surfaces both maps hold are resolved in favour of the map
whose agent saw them more (`resolve_overlap`) instead of being stacked, and what is kept is
concatenated by `merge_maps`. `share_rates` says how fast the share's Gaussians may move in
the refinement that follows on the receiver's views (`gscompress.ops.refine.refine`), which
never drops a Gaussian.

`merge_maps` alone is exact: every Gaussian of both maps, with all its parameters and PWAS
sums, is in the result. Ids stay as they are unless the two maps share some; then the share's
ids are all moved by one offset past the receiver's largest id, so `id - offset` still names
the Gaussian in the sending agent's map.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from gscompress.camera import (
    quat_to_rotmat,
    rotation_angle_deg,
    rotmat_to_quat,
)
from gscompress.errors import MapError, MissingDependencyError, OptionError
from gscompress.gaussians import GaussianMap
from gscompress.ops.icp import DEFAULT_ICP, ICP

MAX_ID = np.iinfo(np.uint32).max


def check_same_world(receiver: str, share: str, what: str, options: tuple[str, ...] = ()) -> None:
    """Refuse to combine maps whose world frames are unknown or not known to agree (`what`
    names the step, and the parameters `options`, as `GscError`'s)."""
    if not receiver or not share:
        raise MapError(
            f"{what}: the world frame of {'the share' if not share else 'the receiver'} is "
            "unknown; only maps anchored to the same frame can be combined (give the transform "
            "between the two frames with `share_transform`)",
            options=(*options, "share_transform"),
        )
    if receiver != share:
        raise MapError(
            f"{what}: the share is expressed in {share!r} but the receiver in {receiver!r}; "
            "maps whose world frames are not known to agree cannot be combined (give the "
            "transform between them with `share_transform`)",
            options=(*options, "share_transform"),
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
    if (
        T.shape != (4, 4)
        or not np.all(np.isfinite(T))
        or not np.allclose(R @ R.T, np.eye(3), atol=1e-6)
        or not np.isclose(np.linalg.det(R), 1.0, atol=1e-6)
    ):
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


FOOTPRINT_RULE = "fits-a-cell-face"
"""How `voxel_evidence` counts a Gaussian for its footprint: whole when its 2-sigma ellipse fits
a cell face, not at all when it does not. (Before, it counted for the part a face holds.)"""

RESOLVE = ("evidence", "receiver", "share", "stack")
"""How a merge treats a surface both maps hold (`MergeOptions.resolve`)."""


@dataclass(frozen=True)
class MergeOptions:
    """How a share is merged into a receiver's map.

    The defaults: aligned, resolved by evidence with a margin, the share's Gaussians moving as
    much as the receiver's views see them. Without the margin (1), they rendered the sender's
    frames of office frag1 better than the exact merge (`EXACT`) and the receiver's a little
    worse (docs/merge.md, "Measured").

    Attributes:
        align: move the share by a local rigid refinement onto the receiver where their
            surfaces overlap (`align_share`) before merging.
        icp: the alignment's ICP (`gscompress.ops.icp.ICP`): "builtin", coloured ICP in numpy
            that needs no extra, or "open3d", Open3D's (the `[align]` extra).
        resolve: where both maps hold the same surface (a voxel of edge `voxel` with
            Gaussians of both): keep only the Gaussians of the map with more evidence there
            ("evidence", `resolve_overlap`), always the receiver's or always the share's; or
            keep both ("stack": the exact concatenation).
        voxel: edge of the voxels that decide what is the same surface (m).
        margin: with "evidence", the share keeps a contested voxel only where its evidence
            there is more than `margin` times the receiver's (1: whichever has more). The
            refinement fits the receiver's views, so a near tie goes to the receiver. At 2
            instead of 1, B receiving A's share at SOG's bytes scored all frames higher on
            average over nine seeds of the room, tabletop and frag1 (docs/merge.md, "A margin on
            the evidence: near ties go to the receiver").
        share_rate: the share's Gaussians move at this fraction of the receiver's learning
            rates in the refinement (0: they keep the sender's values; 1: as the receiver's).
            With `by_view`, the fraction is scaled by how much the receiver's views see each.
        by_view: scale `share_rate` per Gaussian by the receiver's view contribution relative
            to the sender's evidence (`share_rates`).
        footprint: with "evidence", count a Gaussian's evidence in its voxel only when its
            footprint fits a voxel face (`voxel_evidence`). Without it, a folded Gaussian
            (its group's sums on one centre) outweighs the receiver's Gaussians wherever its
            centre lands, and the merge drops the receiver's there, which costs the receiver's
            own frames; counted for the part of its footprint a voxel holds, it still took some
            of them (measured on tabletop in docs/merge.md, "A fold counted for its footprint"
            and "A Gaussian larger than a cell claims none").
    """

    align: bool = True
    icp: str = DEFAULT_ICP
    resolve: str = "evidence"
    voxel: float = 0.04
    margin: float = 2.0
    share_rate: float = 0.0
    by_view: bool = True
    footprint: bool = True

    def check(self) -> None:
        """Raise OptionError for a setting out of range."""
        if self.icp not in ICP:
            raise OptionError(
                f"`icp` is one of {', '.join(ICP)}, got {self.icp!r}", options=("icp",)
            )
        if self.resolve not in RESOLVE:
            raise OptionError(
                f"`resolve` is one of {', '.join(RESOLVE)}, got {self.resolve!r}",
                options=("resolve",),
            )
        if not (math.isfinite(self.voxel) and self.voxel > 0):
            raise OptionError(f"`voxel` must be > 0 (m), got {self.voxel}", options=("voxel",))
        if not (math.isfinite(self.margin) and self.margin >= 1.0):
            raise OptionError(f"`margin` must be >= 1, got {self.margin}", options=("margin",))
        if not 0.0 <= self.share_rate <= 1.0:
            raise OptionError(
                f"`share_rate` must be in [0, 1], got {self.share_rate}", options=("share_rate",)
            )

    def record(self) -> dict[str, Any]:
        """What a provenance step keeps of these options (with `footprint`, the rule it names,
        `FOOTPRINT_RULE`, so that a record made under another rule is not taken for this one)."""
        out = asdict(self)
        if self.footprint:
            out["footprint_rule"] = FOOTPRINT_RULE
        return out


EXACT = MergeOptions(align=False, resolve="stack", share_rate=1.0, by_view=False)
"""Every Gaussian of both maps, all refined alike: the concatenation `merge_maps` gives."""

WITH_SENDER_VIEWS = MergeOptions(align=True, resolve="stack", share_rate=1.0, by_view=False)
"""The merge of a share that carries the sender's keyframes (`gsc share --keyframes`): aligned,
every Gaussian of both maps kept and all refined alike, on the receiver's frames and the
sender's. With the sender's views in the refinement, its Gaussians no longer bend towards the
receiver's alone, and stacking loses nothing: B receiving A's whole map and A's keyframes
came within 0.5 dB of the centralised map on both agents' frames of the synthetic room,
tabletop and office frag1, where the default merge with the same keyframes missed on
tabletop's and frag1's A frames (docs/merge.md, "A share that carries the sender's
keyframes")."""

OPAQUE = 0.5
"""Gaussians at least this opaque are the surface that `align_share` fits."""


def align_share(
    receiver: GaussianMap,
    share: GaussianMap,
    max_distance: float = 0.05,
    min_pairs: int = 50,
    icp: str = DEFAULT_ICP,
) -> tuple[np.ndarray, dict[str, Any]]:
    """A local rigid refinement of the share onto the receiver where their surfaces overlap.

    Two agents anchored in one world frame still sit centimetres apart (each map agrees with
    its own trajectory). The step is `gsc align`'s local one, `gscompress.ops.align.
    refine_alignment` (coloured ICP from the identity, on the opaque Gaussians' centres and
    colours, correspondences within `max_distance` and then half of it, by the implementation
    `icp`): one piece of code serves both. With fewer than `min_pairs` of the share's opaque
    centres within `max_distance` of the receiver's (maps that hardly overlap), the identity is
    returned.

    Returns:
        T_receiver_share [4, 4] and {"align_kept", "align_pairs", "align_rmse_before_cm",
        "align_rmse_after_cm", "align_shift_cm", "align_angle_deg"}: the pairs and their RMS
        distance are the share's opaque centres within `max_distance` of the receiver's
        nearest one, before and after. The step is kept only where it brings the share's
        centres closer to the receiver's (`fit_cost`); else the identity, `align_kept` False.

    Raises:
        MissingDependencyError: `icp` "open3d" without Open3D (`pip install
            'gscompress[align]'`).
    """
    from scipy.spatial import cKDTree

    from gscompress.ops.align import AlignOptions, map_cloud, points_fit, refine_alignment

    def cloud(g: GaussianMap) -> Any:
        return map_cloud(g.means, g.colors(), g.opacities(), min_opacity=OPAQUE)

    src, dst = cloud(share), cloud(receiver)
    stats: dict[str, Any] = {"align_pairs": 0}
    if len(src.points) < min_pairs or len(dst.points) < min_pairs:
        return np.eye(4), stats
    tree = cKDTree(dst.points)
    n = len(src.points)
    before = points_fit(src.points, tree, np.eye(4), max_distance)
    if round(before[0] * n) < min_pairs:
        return np.eye(4), stats
    options = AlignOptions(voxel=max_distance, icp=icp)
    T = refine_alignment(src, dst, np.eye(4), options).T_target_source
    after = points_fit(src.points, tree, T, max_distance)
    kept = fit_cost(*after, max_distance) < fit_cost(*before, max_distance)
    if not kept:  # (the step slid or turned the share off the receiver: left where it was)
        T, after = np.eye(4), before
    stats.update(
        align_kept=kept,
        align_pairs=round(after[0] * n),
        align_rmse_before_cm=round(100.0 * before[1], 3),
        align_rmse_after_cm=round(100.0 * after[1], 3),
        align_shift_cm=round(100.0 * float(np.linalg.norm(T[:3, 3])), 3),
        align_angle_deg=round(float(rotation_angle_deg(T[:3, :3])), 4),
    )
    return T, stats


def fit_cost(fraction: float, rms: float, max_distance: float) -> float:
    """Mean over the share's centres of the squared distance to the receiver's nearest, each
    capped at `max_distance`, from `points_fit`'s figures (the `fraction` within it, at `rms`):
    what an alignment must lower to be kept. Coloured ICP on a flat scene can slide or turn the
    share in the plane, its centres ending farther from the receiver's than before (tabletop:
    docs/merge.md, "Aligned by `gsc align`'s local step")."""
    return fraction * rms**2 + (1.0 - fraction) * max_distance**2


def voxel_keys(means: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 key per point: the voxel of edge `voxel` (m) it falls in."""
    cells = np.floor(means.astype(np.float64) / voxel).astype(np.int64)
    cells -= cells.min(axis=0) if len(cells) else 0
    span = cells.max(axis=0) + 1 if len(cells) else np.ones(3, np.int64)
    return (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]


def voxel_evidence(gaussians: GaussianMap, voxel: float | None) -> np.ndarray:
    """[N] float64 evidence of each Gaussian (its `alpha_t_sum`) for the voxel of edge `voxel`
    (m) that holds its centre: all of it when its footprint fits a voxel face, 4 pi s1 s2 <=
    voxel^2 (s1 >= s2 its two largest standard deviations, so 4 pi s1 s2 is the area of its
    2-sigma ellipse), none when it does not. A Gaussian larger than a voxel, such as a fold of
    many (whose sums are its group's), is coarser than the surfaces the voxels tell apart: it
    claims no voxel from Gaussians that draw it finely, and keeps its place where the other
    map has nothing. None: every Gaussian counts whole."""
    evidence = np.asarray(gaussians.alpha_t_sum, np.float64)
    if voxel is None or not len(gaussians):
        return evidence
    s = np.sort(gaussians.scales().astype(np.float64), axis=1)
    area = 4.0 * np.pi * s[:, -1] * s[:, -2]
    return np.where(area <= voxel * voxel, evidence, 0.0)


def resolve_overlap(
    receiver: GaussianMap,
    share: GaussianMap,
    receiver_evidence: np.ndarray,
    share_evidence: np.ndarray,
    voxel: float = 0.04,
    margin: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Which Gaussians to keep where both maps hold the same surface.

    Space is cut into voxels of edge `voxel` (m). In a voxel where both maps have Gaussians,
    only the map whose Gaussians there carry more evidence (the summed
    `*_evidence` of its Gaussians in the voxel) keeps its Gaussians, the share only where its
    evidence is more than `margin` times the receiver's; elsewhere both keep theirs.

    Returns:
        Boolean keep masks for the receiver's and the share's Gaussians, and
        {"overlap_voxels", "receiver_dropped", "share_dropped"}.
    """
    keep_r = np.ones(len(receiver), bool)
    keep_s = np.ones(len(share), bool)
    stats = {"overlap_voxels": 0, "receiver_dropped": 0, "share_dropped": 0}
    if not len(receiver) or not len(share):
        return keep_r, keep_s, stats
    keys = voxel_keys(np.concatenate([receiver.means, share.means]), voxel)
    n = len(receiver)
    cells, inverse = np.unique(keys, return_inverse=True)
    owner_r = np.zeros(len(cells), bool)
    owner_s = np.zeros(len(cells), bool)
    owner_r[inverse[:n]] = True
    owner_s[inverse[n:]] = True
    evidence = np.concatenate([receiver_evidence, share_evidence]).astype(np.float64)
    sum_r = np.bincount(inverse[:n], evidence[:n], minlength=len(cells))
    sum_s = np.bincount(inverse[n:], evidence[n:], minlength=len(cells))
    contested = owner_r & owner_s
    share_wins = contested & (sum_s > margin * sum_r)
    receiver_wins = contested & ~share_wins
    keep_r = ~share_wins[inverse[:n]]
    keep_s = ~receiver_wins[inverse[n:]]
    stats = {
        "overlap_voxels": int(contested.sum()),
        "receiver_dropped": int((~keep_r).sum()),
        "share_dropped": int((~keep_s).sum()),
    }
    return keep_r, keep_s, stats


def combine(
    receiver: GaussianMap, share: GaussianMap, options: MergeOptions
) -> tuple[GaussianMap, np.ndarray, int, dict[str, Any]]:
    """The receiver's map with the share merged in as `options` say (before any refinement).

    The share is aligned to the receiver (`align_share`), the surfaces both hold are resolved
    (`resolve_overlap`, by each Gaussian's `alpha_t_sum`: how much its own agent's frames saw
    of it, counted only where its footprint fits a voxel with `options.footprint`,
    `voxel_evidence`), and what is kept is concatenated (`merge_maps`).

    Returns:
        The merged map, a boolean mask of its rows that came from the share, the id offset
        given to the share, and what was done (alignment figures, Gaussians dropped; with
        `align_transform`, the [4, 4] rigid transform the share was moved by, as nested
        lists, when the alignment moved it).
    """
    options.check()
    stats: dict[str, Any] = {}
    if options.align and len(receiver) and len(share) and share.sh_degree == 0:
        try:
            T, found = align_share(receiver, share, max_distance=options.voxel, icp=options.icp)
        except MissingDependencyError as exc:
            raise MissingDependencyError(
                f"{exc}; or merge without aligning (`no_align`)",
                options=(*exc.options, "no_align"),
            ) from None
        stats.update(found)
        if found["align_pairs"]:
            share = transform_map(share, T)
            stats["align_transform"] = np.round(T, 12).tolist()
    keep_r = np.ones(len(receiver), bool)
    keep_s = np.ones(len(share), bool)
    if options.resolve == "evidence":
        voxel = options.voxel if options.footprint else None
        keep_r, keep_s, dropped = resolve_overlap(
            receiver,
            share,
            voxel_evidence(receiver, voxel),
            voxel_evidence(share, voxel),
            options.voxel,
            options.margin,
        )
        stats.update(dropped)
    elif options.resolve != "stack":
        ones_r = np.ones(len(receiver), np.float64)
        ones_s = np.ones(len(share), np.float64)
        share_first = options.resolve == "share"
        keep_r, keep_s, dropped = resolve_overlap(
            receiver,
            share,
            ones_r * (0.0 if share_first else 1.0),
            ones_s * (1.0 if share_first else 0.0),
            options.voxel,
        )
        stats.update(dropped)
    merged, offset = merge_maps(receiver.select(keep_r), share.select(keep_s))
    from_share = np.zeros(len(merged), bool)
    from_share[int(keep_r.sum()) :] = True
    return merged, from_share, offset, stats


def share_rates(
    from_share: np.ndarray,
    options: MergeOptions,
    receiver_views: np.ndarray | None = None,
    sender_evidence: np.ndarray | None = None,
) -> np.ndarray | None:
    """Per-Gaussian factors on the refinement's steps: 1 for the receiver's Gaussians,
    `options.share_rate` for the share's; with `options.by_view`, at least the receiver's share
    of the evidence, v / (v + e), with v what the receiver's views see of it
    (`receiver_views`) and e what the sender's frames saw (`sender_evidence`, its alpha_t_sum).
    None when every factor is 1."""
    rates = np.where(from_share, options.share_rate, 1.0)
    if options.by_view and receiver_views is not None and sender_evidence is not None:
        v = np.asarray(receiver_views, np.float64)
        e = np.asarray(sender_evidence, np.float64)
        ratio = np.divide(v, v + e, out=np.zeros_like(v), where=(v + e) > 0)
        rates = np.where(from_share, np.maximum(rates, ratio), rates)
    return None if np.all(rates == 1.0) else rates.astype(np.float32)
