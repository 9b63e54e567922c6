"""`gsc prune`: a log with its map cut to a retention ratio (numpy + mcap only; torch only to
refine what it keeps, when asked)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gscompress.gaussians import GaussianMap
from gscompress.io.compact import COMPACT_DEFAULTS, CompactOptions
from gscompress.ops.fold import cut_map, cut_pool
from gscompress.ops.refine import MapRefiner, refined
from gscompress.pipeline.logs import rewrite_map
from gscompress.selection import check_ratio, keep_count, selection_scores


def prune_log(
    src: str | Path,
    dst: str | Path,
    keep: float,
    *,
    by: str = "pwas",
    seed: int = 0,
    codec: str | None = None,
    options: CompactOptions = COMPACT_DEFAULTS,
    refine: MapRefiner | None = None,
    map_only: bool = False,
    fold: bool = True,
    command: str = "",
    force: bool = False,
) -> dict[str, Any]:
    """Keep the `keep` fraction of a log's map with the highest `by` scores (`cut_map`: with
    `fold`, what is dropped is folded into the kept Gaussians).

    The last `/gaussians` snapshot is replaced by its pruned version (same log time), stored in
    `codec` (None: the codec of the map it replaces); every other message, earlier snapshots
    included, passes through unchanged (with `map_only`, only the calibration does: see
    `rewrite_map`). `refine` (a `gscompress.pipeline.refining.LogRefiner`) refines the kept
    Gaussians before they are written; it never adds or drops one.
    """
    check_ratio(keep, "`keep`", ("keep",))

    def prune(full: GaussianMap) -> tuple[GaussianMap, dict[str, Any]]:
        scores = selection_scores(full, by, seed)
        kept = cut_map(cut_pool(full, refine), keep_count(len(full), keep), scores, fold)
        return refined(
            kept, {"kept": len(kept), "total": len(full), "fold": fold}, refine, teacher=full
        )

    operation: dict[str, Any] = {
        "name": "prune",
        "keep": keep,
        "by": by,
        "seed": seed,
        "fold": fold,
    }
    if refine is not None:
        operation["refine"] = refine.record()
    if map_only:
        operation["map_only"] = True
    return rewrite_map(
        src,
        dst,
        operation,
        prune,
        codec=codec,
        options=options,
        command=command,
        force=force,
        map_only=map_only,
    )
