"""`gsc share`: the budgeted top-K share of a log's map for another agent (numpy + mcap only;
torch only to refine, solve or rank for a receiver, when asked).

The command is `share_log`, here; its parts:

- `options`: `ShareOptions`, the share's settings, their checks and the record it keeps;
- `cut`: `ShareCut`, the share file of the K best Gaussians for any K (what a byte budget
  searches over);
- `solve`: the byte-budget solver of `gsc share --solve` (the codec and PWAS state that give
  the best picture for the bytes);
- `receiver`: a receiver-aware share (`--for`): the receiver's request, and what it has not seen;
- `formats`: a whole map as it would cross the link in a reference format (the experiment's).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.errors import OptionError
from gscompress.gaussians import GaussianMap
from gscompress.io.codec import get_codec
from gscompress.io.files import check_output, sha256, write_bytes_atomic
from gscompress.io.keyframes import CarriedFrame
from gscompress.io.mcap_log import LogMetadata, read_map
from gscompress.io.ply import write_ply
from gscompress.ops.budget import Budget
from gscompress.ops.refine import MapRefiner
from gscompress.pipeline.share.cut import DEFAULTS, ShareCut
from gscompress.pipeline.share.options import ShareOptions
from gscompress.pipeline.share.receiver import read_request


def share_log(
    src: str | Path,
    dst: str | Path,
    budget: str | float | Budget,
    options: ShareOptions = DEFAULTS,
    *,
    ply: str | Path | None = None,
    refine: MapRefiner | None = None,
    solve: dict[str, Any] | None = None,
    align_to: str | Path | None = None,
    command: str = "",
    force: bool = False,
    source: tuple[GaussianMap, LogMetadata] | None = None,
    carry: tuple[list[CarriedFrame], Intrinsics] | None = None,
    receiver: str | Path | None = None,
    device: str = "auto",
    progress: Callable[[int], object] | None = None,
) -> dict[str, Any]:
    """Cut the budgeted top-K share of a log's map for another agent (MCAP, and PLY if asked).

    The share is a small log: the metadata record (source, strategy, budget, counts, provenance;
    not the sender's config, which the receiver does not use) and one `/gaussians` snapshot
    holding the selected Gaussians with their PWAS state (and ids if asked).

    Args:
        src: the log whose map (last snapshot) is shared.
        dst: the share (MCAP).
        budget: a fraction of the Gaussians in (0, 1], or bytes (`"2MB"`, `"1.5MiB"`, or
            `"5%bytes"` of the map's fp32 message; see `Budget`). A byte budget bounds the whole
            share file as written (framing, schema, metadata and map: the bytes that cross the
            link), which holds the most Gaussians that fit.
        options: how the map is ranked, cut and encoded (`ShareOptions`: strategy, codec,
            sums, ids, seed, fold, spread).
        ply: also write the share as a float32 3DGS PLY (the decoded values).
        refine: refines the selected Gaussians before they are sent (a
            `gscompress.pipeline.refining.LogRefiner` on the sender's frames); a byte budget
            still bounds the file of the refined values (the last few may then be left out).
        solve: the byte-budget solver's record of how it chose the codec (for the provenance;
            see `gscompress.pipeline.share.solve`).
        align_to: a log of the receiving agent whose world frame differs: the share is cut
            in that log's frame, the transform found by `gsc align`'s aligner (recorded in the
            provenance with its overlap and residual); the receiver then merges it as is.
        command: command line for the provenance record.
        force: overwrite existing outputs.
        source: the map and metadata of `src` when they are already read (a map file's map,
            with `LogMetadata()`: see `ShareCut`).
        carry: keyframes of the sender to send along, and their camera
            (`gscompress.pipeline.logs.carried_keyframes`; `gscompress.io.keyframes`): a
            byte budget counts their bytes too, leaving fewer Gaussians.
        receiver: the receiving agent's log: the Gaussians its views do not draw are sent
            first (`gscompress.pipeline.share.receiver`; needs torch, rendered on `device`); a byte
            budget counts its request's bytes too. In its own world frame, which must be the
            map's unless `align_to` gives the transform.
        progress: called with how many cuts a byte budget has tried so far (each a fold and
            an encoding of the whole share), as its search goes (0: it starts).

    Raises:
        InputError: bad budget, codec or strategy (OptionError: --ply equal to the MCAP
            output).
        BudgetError: the budget holds no Gaussian.
        MapError: at fp16, a selected value beyond the float16 range.
    """
    budget = Budget.parse(budget)
    options.check()
    _check_outputs(src, dst, ply, [p for p in (src, align_to, receiver) if p is not None], force)
    align = None if align_to is None else share_alignment(src, align_to)
    cut = ShareCut(
        src,
        budget,
        options,
        refine=refine,
        solve=solve,
        command=command,
        source=source,
        align=align,
        carry=carry,
        receiver=None if receiver is None else read_request(receiver),
        device=device,
    )
    data, shared, results = cut.file(_count(cut, refine, progress))
    limit = cut.budget.budget_bytes
    if limit is not None and len(data) > limit:
        raise AssertionError(f"share of {len(data)} B exceeds {limit} B")
    results["file_bytes"] = len(data)
    _write(data, shared, dst, ply, options.codec, src, force)
    return {"output": str(dst), "ply": None if ply is None else str(ply), **results}


def _check_outputs(
    src: str | Path,
    dst: str | Path,
    ply: str | Path | None,
    inputs: list[str | Path],
    force: bool,
) -> None:
    """Refuse a PLY output that is the MCAP one, and outputs that would overwrite an input or
    an existing file (without `force`)."""
    outputs = [(dst, ".mcap")] if ply is None else [(dst, ".mcap"), (ply, ".ply")]
    if ply is not None and Path(ply).resolve() == Path(dst).resolve():
        raise OptionError("`ply` must differ from the MCAP output", options=("ply",))
    for path, suffix in outputs:
        check_output(path, inputs, force, suffix)


def _count(
    cut: ShareCut, refine: MapRefiner | None, progress: Callable[[int], object] | None
) -> int:
    """How many Gaussians the share sends: the budget's count (a byte budget's search reported
    to `progress`), then the count that fits once they are refined (`ShareCut.refined`)."""
    searched = cut.budget.budget_bytes is not None
    count = cut.budget.count(len(cut.full), _counted(cut.size, progress) if searched else cut.size)
    if refine is not None:
        count = cut.refined(count, refine)
    return count


def _write(
    data: bytes,
    shared: GaussianMap,
    dst: str | Path,
    ply: str | Path | None,
    codec: str,
    src: str | Path,
    force: bool,
) -> None:
    """Write the share file and, with `ply`, its decoded values as a PLY: both or neither."""
    write_bytes_atomic(dst, data)
    if ply is not None:
        try:  # the receiver's values: what the share decodes to
            received = shared if get_codec(codec).lossless else read_map(dst)
            write_ply(received, ply, inputs=(src,), force=force)
        except BaseException:  # a share is written whole or not at all
            Path(dst).unlink(missing_ok=True)
            raise


def _counted(
    size: Callable[[int], int], progress: Callable[[int], object] | None
) -> Callable[[int], int]:
    """`size`, reporting to `progress` how many times it has been called (a budget's search)."""
    if progress is None:
        return size
    tried = itertools.count(1)
    progress(0)

    def counted(count: int) -> int:
        bytes_ = size(count)
        progress(next(tried))
        return bytes_

    return counted


def share_alignment(source: str | Path, target: str | Path) -> tuple[np.ndarray, dict[str, Any]]:
    """`gsc share --align-to`: the transform from `source`'s frame to `target`'s, and what the
    share records of it (target name, sha256, world frame, figures)."""
    from gscompress.pipeline.aligning import align_logs_transform

    T, record = align_logs_transform(source, target)
    keep = ("overlap", "residual", "inliers", "ambiguity", "conditioning", "target_world_frame")
    out = {k: record[k] for k in keep}
    out.update(
        target=Path(target).name, target_sha256=sha256(target), transform=np.round(T, 12).tolist()
    )
    return T, out
