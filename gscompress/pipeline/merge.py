"""`gsc merge`: inject another agent's share into a receiver's map and refine it there.

The receiver's log is copied with its map (the last snapshot) replaced by the merge of its map
and the share (`gscompress.ops.merge.combine`: aligned, the surfaces both hold resolved),
refined on the receiver's own frames (all of them, or its keyframes only) at the receiver's
estimated poses, the share's Gaussians held still or slowed (`MergeOptions.share_rate`). Both
inputs are in the output's provenance: the receiver as the parent, the share (name, sha256, id
offset) and the merge's options in the merge operation. The refinement is
`gscompress.pipeline.refining`'s, which prune and share use too. Maps are merged only when their
world frames agree (`LogMetadata.world_frame`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import OptionError
from gscompress.gaussians import GaussianMap
from gscompress.io.files import check_output
from gscompress.io.mcap_log import LogReader
from gscompress.ops.merge import WITH_SENDER_VIEWS, MergeOptions, combine, share_rates
from gscompress.pipeline.logs import ReceivedShare, check_same_camera, read_share, rewrite_map
from gscompress.pipeline.refining import DEFAULT_LR_FINAL, RefineOptions

DEFAULT_REFINE_VIEWS = "frames"
"""What a merge refines on unless told (`REFINE_VIEWS`): every frame of the receiver's subset.
Keyframes alone are few, and refining on them lowered the receiver's PSNR on its other frames;
every frame raises it (docs/design-experiments.md, "Why merges decay their learning rates")."""


def merge_logs(
    receiver: str | Path,
    share: str | Path | None,
    dst: str | Path,
    *,
    seq: str | Path | None = None,
    frames: str | None = None,
    size: tuple[int, int] | None = None,
    iters: int = 200,
    views: str = DEFAULT_REFINE_VIEWS,
    lr_final: float = DEFAULT_LR_FINAL,
    device: str = "auto",
    backend: str | None = None,
    seed: int = 0,
    share_transform: str | Path | None = None,
    codec: str | None = None,
    merge: MergeOptions | dict[str, Any] | None = None,
    keyframes: bool = True,
    recording: Any = None,
    command: str = "",
    force: bool = False,
    progress: Callable[[int, int], object] | None = None,
) -> dict[str, Any]:
    """Merge the share log `share` into the receiver log `receiver` and write `dst`.

    Args:
        receiver: the receiving agent's SLAM log (map, poses, config).
        share: a share (`gsc share`) or any log whose last snapshot is the map to inject;
            None refines the receiver's map alone (the control of a merge: the same refinement
            without a share).
        dst: the output log.
        seq: the receiver's sequence (needed when `iters` > 0).
        frames: the receiver's frame subset (default: the one recorded in its log).
        size: working size (default: the receiver's config).
        iters: refinement iterations on the receiver's views (0: concatenate only).
        views: "frames" (every frame of the receiver's subset) or "keyframes" (its keyframes).
        lr_final: the refinement's learning rates decay geometrically to this fraction of
            their starting value (the receiver's mapping rates); 1 keeps them constant.
        device: torch device, or "auto".
        backend: render backend of the refinement (default: the receiver's config's).
        seed: seed of the view order.
        share_transform: a file with the rigid transform from the share's world frame to the
            receiver's (4x4 or TUM `tx ty tz qx qy qz qw`), for maps whose frames differ.
        codec: how the merged map is stored (None: as the receiver's map).
        merge: how the share is aligned, resolved against the receiver's map and refined
            (`gscompress.ops.merge.MergeOptions`; None: its defaults, or `WITH_SENDER_VIEWS`
            when the share carries keyframes the refinement uses; a dict: those with the
            fields it names changed).
        keyframes: also refine on the sender's keyframes the share carries (`gsc share
            --keyframes`), at their poses moved as the share is; their timestamps are in the
            merge's provenance (`carried_ns`), and `gsc eval` leaves those frames out.
        recording: a recording's topics, pairing and ground truth when `seq` is one
            (`gscompress.datasets.RecordingOptions`; None: those the receiver's run recorded).
        command: the command line, for the metadata.
        force: overwrite `dst`.
        progress: called with (iterations done, iterations) during refinement.

    Returns:
        Output path, Gaussian counts (receiver, share, merged), the id offset given to the
        share, and the refinement's first/last loss, views and render backend.
    """
    options = RefineOptions(
        iters, views, lr_final, frames, size, device, backend, seed, recording=recording
    )
    _check_inputs(receiver, share, dst, seq, share_transform, options, force)
    with LogReader(receiver) as receiver_log:
        meta = receiver_log.metadata
        receiver_log.require_snapshots()
    received = None
    if share is not None:  # (the keyframes serve the refinement only)
        received = read_share(
            share, meta.world_frame, "merge", share_transform, keyframes=keyframes and iters > 0
        )
    carried = [] if received is None else received.carried
    how = (
        merge
        if isinstance(merge, MergeOptions)
        else replace(WITH_SENDER_VIEWS if carried else MergeOptions(), **(merge or {}))
    )
    how.check()
    refiner = None
    if iters > 0:
        assert seq is not None
        refiner = _receiver_refiner(receiver, seq, options, progress, received, share)
    merge_into = functools.partial(_merge_into, received=received, how=how, refiner=refiner)
    share_record = {"share": None} if received is None else received.record
    operation = {"name": "merge", **share_record, **options.record(), **how.record()}
    return rewrite_map(
        receiver, dst, operation, merge_into, codec=codec, command=command, force=force
    )


def _check_inputs(
    receiver: str | Path,
    share: str | Path | None,
    dst: str | Path,
    seq: str | Path | None,
    share_transform: str | Path | None,
    options: RefineOptions,
    force: bool,
) -> None:
    """Refuse `merge_logs`' refinement options out of range, a refinement without the receiver's
    sequence, an output that would overwrite an input, and a share that is the receiver."""
    options.check()
    if options.iters > 0 and seq is None:
        raise OptionError(
            "refining needs the receiver's sequence: pass `seq` (or `iters` 0)",
            options=("seq", "iters"),
        )
    inputs = [receiver] + [p for p in (share, seq, share_transform) if p is not None]
    check_output(dst, inputs, force, ".mcap")
    if share is not None and Path(share).exists() and Path(share).samefile(receiver):
        raise OptionError(f"{share} is the receiver log itself: merging it would double its map")


def _receiver_refiner(
    receiver: str | Path,
    seq: str | Path,
    options: RefineOptions,
    progress: Callable[[int, int], object] | None,
    received: ReceivedShare | None,
    share: str | Path | None,
) -> Any:
    """The refinement on the receiver's frames (`LogRefiner`), refusing keyframes the share
    carries from another camera than the receiver's."""
    from gscompress.pipeline.refining import LogRefiner

    instead = "merge with `iters` 0 to concatenate only"
    refiner = LogRefiner(receiver, seq, options, progress, instead)
    if received is not None and received.carried:
        check_same_camera(
            received.camera,
            refiner.intrinsics,
            str(share),
            "the merge refines",
            "merge with `no_keyframes`",
            ("no_keyframes",),
        )
    return refiner


def _merge_into(
    own: GaussianMap, received: ReceivedShare | None, how: MergeOptions, refiner: Any
) -> tuple[GaussianMap, dict[str, Any]]:
    """The receiver's map `own` with the share combined into it (`combine`; an empty share
    without one) and refined on the receiver's frames (and the keyframes the share carries,
    moved as the merge aligned it) by `refiner` when there is one; and what to record."""
    shared = received.gaussians if received is not None else None
    carried = received.carried if received is not None else []
    share_map = shared if shared is not None else GaussianMap.empty(own.isotropic, own.sh_degree)
    merged, from_share, offset, done = combine(own, share_map, how)
    results: dict[str, Any] = {
        "receiver": len(own),
        "share": len(share_map),
        "gaussians": len(merged),
        "id_offset": offset,
        **done,
    }
    if refiner is None:
        return merged, results
    if carried:
        T_align = np.asarray(done.get("align_transform", np.eye(4)), np.float64)
        refiner.carry([f.moved(T_align) for f in carried])
    seen = refiner.contributions(merged) if how.by_view and from_share.any() else None
    rates = share_rates(from_share, how, seen, merged.alpha_t_sum)
    merged, stats = refiner(merged, rates)
    return merged, {**results, **{f"refine_{k}": v for k, v in stats.items()}}
