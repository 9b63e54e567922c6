"""The byte-budget solver of `gsc share --solve`: the count, codec and PWAS state that give the
best picture for the bytes (needs torch, to render).

Every candidate (codec, sums, fold) that the options allow is cut to the most Gaussians whose share
file fits the budget (`ShareCut`), decoded as the receiver would decode it, rendered at a few of
the sender's keyframes and scored by PSNR: against the keyframes' own images when the sender's
sequence is given, else against the renders of the sender's whole map at the same poses. More
Gaussians in a smaller codec against fewer, exact ones is the trade the solver settles; within
one codec more Gaussians never draw less, so each candidate is taken at its largest count.
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import BudgetError, InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.codec import CODECS, sums_choices
from gscompress.io.files import check_output
from gscompress.io.mcap_log import LogReader, decoded_map
from gscompress.ops.budget import Budget
from gscompress.ops.refine import MapRefiner
from gscompress.pipeline.logs import spread_keyframes
from gscompress.pipeline.share import share_log
from gscompress.pipeline.share.cut import DEFAULTS, ShareCut
from gscompress.pipeline.share.options import SOLVED, ShareOptions

log = logging.getLogger(__name__)

CANDIDATES = tuple(
    (codec, sums, folded)
    for codec in reversed(CODECS)
    for sums in sorted(sums_choices(codec))
    for folded in (True, False)
)
"""(codec, sums, fold) the solver weighs, the smallest codec first (a codec that always carries
the sums is weighed with them only; fold: what the share leaves out folded into what it sends,
`gscompress.ops.fold`)."""

SOLVE_VIEWS = 4
"""Keyframes the candidates are rendered at, spread over the sender's trajectory."""


@dataclass(frozen=True)
class Candidate:
    """One weighed share: its codec, whether it carries the PWAS sums, whether it folds what it
    leaves out into what it sends, its count, its file's
    bytes and the PSNR of its decoded map at the solver's views."""

    codec: str
    sums: bool
    fold: bool
    count: int
    file_bytes: int
    psnr: float


def solve_share(
    src: str | Path,
    budget: Budget,
    options: ShareOptions = DEFAULTS,
    *,
    fixed: Collection[str] = (),
    seq: str | Path | None = None,
    views: int = SOLVE_VIEWS,
    device: str = "auto",
    recording: Any = None,
) -> tuple[Candidate, list[Candidate], dict[str, Any]]:
    """Weigh the candidate shares of `src`'s map under `budget` and pick the best picture.

    Args:
        src: the sender's SLAM log.
        budget: the share budget (bytes, or a fraction of the map's fp32 bytes; a fraction of
            the Gaussians fixes the count, leaving the codec to choose).
        options: how Gaussians are ranked (strategy, seed, spread: as `gsc share`) and whether
            compact candidates send the ids (`share_log`; not weighed: they draw nothing).
            Its codec, sums and fold are the solver's to choose (`SOLVED`) unless `fixed`.
        fixed: those of `SOLVED` that `options` fixes: the search is constrained to its codec
            / PWAS state / folding (none: any).
        seq: the sender's sequence: score against its keyframe images (else against the whole
            map's renders).
        views: how many keyframes to render at.
        device: torch device.
        recording: a recording's topics, pairing and ground truth when `seq` is one
            (`gscompress.datasets.RecordingOptions`; None: those the log's run recorded).

    Returns:
        The chosen candidate, every candidate weighed (best first), and a record for the
        provenance (`against`, `views`, the candidates).

    Raises:
        BudgetError: no candidate holds one Gaussian.
        InputError: the log has no poses; `views` below 1; `fixed` names a setting the solver
            does not choose.
    """
    from gscompress.metrics import psnr
    from gscompress.ops.evaluate import render_view
    from gscompress.ops.score import activated_tensors
    from gscompress.render import resolve_device

    if views < 1:
        raise InputError(f"the solver needs at least one view, got {views}")
    if not set(fixed) <= set(SOLVED):
        raise InputError(f"the solver chooses {', '.join(SOLVED)}; got {', '.join(fixed)}")
    wanted = tuple(getattr(options, name) if name in fixed else None for name in SOLVED)
    poses, targets, masks, intrinsics = _views(src, seq, views, recording)
    torch_device = resolve_device(device, "auto")
    if targets is None:
        with LogReader(src) as reader:
            full = reader.read_map()
        params = activated_tensors(full, torch_device)
        targets = [render_view(params, pose, intrinsics)[0] for pose in poses]
    weighed: list[Candidate] = []
    refusals: list[str] = []  # (one per candidate the budget cannot hold)
    for cand_codec, cand_sums, cand_fold in CANDIDATES:
        chosen = zip(wanted, (cand_codec, cand_sums, cand_fold), strict=True)
        if any(w is not None and w != c for w, c in chosen):
            continue
        candidate = replace(options, codec=cand_codec, sums=cand_sums, fold=cand_fold)
        cut = ShareCut(src, budget, candidate)
        try:
            count = cut.budget.count(len(cut.full), cut.size)
        except BudgetError as exc:
            refusals.append(f"{cand_codec}: {exc}")
            continue
        data, selected, _ = cut.file(count)
        received: GaussianMap = decoded_map(selected, cand_codec, sums=cand_sums)
        params = activated_tensors(received, torch_device)
        scores = [
            psnr(render_view(params, pose, intrinsics)[0], target, mask)
            for pose, target, mask in zip(poses, targets, masks, strict=True)
        ]
        weighed.append(
            Candidate(cand_codec, cand_sums, cand_fold, count, len(data), float(np.mean(scores)))
        )
        log.info(
            "solver: %s%s%s, %d Gaussians, %d B: %.2f dB",
            cand_codec,
            "" if cand_sums else " (no sums)",
            " folded" if cand_fold else "",
            count,
            len(data),
            weighed[-1].psnr,
        )
    if not weighed:
        raise BudgetError(refusals[0])  # (the smallest codec's: the others hold no more)
    weighed.sort(key=lambda c: (-c.psnr, c.file_bytes))
    record = {
        "against": "frames" if seq is not None else "map renders",
        "views": len(poses),
        "candidates": [asdict(c) for c in weighed],
    }
    return weighed[0], weighed, record


def _views(
    src: str | Path, seq: str | Path | None, views: int, recording: Any = None
) -> tuple[list[np.ndarray], list[np.ndarray] | None, list[np.ndarray], Any]:
    """Poses of `views` keyframes spread over the log, with their images and valid-depth masks
    when `seq` is given (else None and all-pixel masks), and the intrinsics."""
    chosen = spread_keyframes(src, views, seq, "the solver", recording)
    if chosen.frames is None:
        shape = (chosen.intrinsics.height, chosen.intrinsics.width)
        return chosen.poses, None, [np.ones(shape, bool)] * len(chosen.poses), chosen.intrinsics
    return (
        chosen.poses,
        [f.color for f in chosen.frames],
        [f.depth > 0 for f in chosen.frames],
        chosen.intrinsics,
    )


def share_solved(
    src: str | Path,
    dst: str | Path,
    budget: str | float | Budget,
    options: ShareOptions = DEFAULTS,
    *,
    fixed: Collection[str] = (),
    seq: str | Path | None = None,
    views: int = SOLVE_VIEWS,
    device: str = "auto",
    ply: str | Path | None = None,
    refine: MapRefiner | None = None,
    align_to: str | Path | None = None,
    carry: Any = None,
    receiver: str | Path | None = None,
    command: str = "",
    force: bool = False,
    recording: Any = None,
) -> dict[str, Any]:
    """`share_log` with the codec and PWAS state the solver chose (`solve_share`, of `options`
    with those of `SOLVED` in `fixed` kept), the solver's record in the provenance and the
    predicted PSNR in the results (`predicted_psnr`, and `solved_against`: "frames" or "map
    renders"). Keyframes to `carry` are weighed as the Gaussians' bytes are not: the solver
    compares the codecs without them, and the share then holds the most Gaussians that fit
    beside them. So is a `receiver` (`share_log`): the codecs are compared on the sender's
    views, and the share then sends first what the receiver has not seen. `recording`: as
    `solve_share`'s."""
    budget = Budget.parse(budget)
    check_output(dst, [src], force, ".mcap")  # before the renders, not after them
    best, _weighed, record = solve_share(
        src, budget, options, fixed=fixed, seq=seq, views=views, device=device, recording=recording
    )
    record["predicted_psnr"] = best.psnr
    chosen = replace(options, codec=best.codec, sums=best.sums, fold=best.fold)
    result = share_log(
        src,
        dst,
        budget,
        chosen,
        ply=ply,
        refine=refine,
        solve=record,
        align_to=align_to,
        carry=carry,
        receiver=receiver,
        device=device,
        command=command,
        force=force,
    )
    result.update(predicted_psnr=best.psnr, solved_against=record["against"])
    return result
