"""The prune and share the viewer previews, cut by the code `gsc prune` and `gsc share` run
(`select_top`, `ShareCut`), and written by it (`prune_log`, `share_log`)."""

from __future__ import annotations

import shlex
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.gaussians import GaussianMap
from gscompress.io.codec import CODECS, sums_choices
from gscompress.io.files import check_output
from gscompress.io.map_files import write_map_file
from gscompress.io.mcap_log import LogMetadata
from gscompress.ops.budget import Budget
from gscompress.pipeline.prune import prune_log
from gscompress.pipeline.share import share_log
from gscompress.pipeline.share.cut import ShareCut
from gscompress.pipeline.share.options import ShareOptions
from gscompress.selection import select_top

SHARE_CODECS = tuple((codec, sums) for codec in reversed(CODECS) for sums in sums_choices(codec))
"""(codec, sums) pairs a share's size is shown in."""


def codec_label(codec: str, sums: bool) -> str:
    """How a (codec, sums) pair is named in the viewer: `compact`, `compact, no sums`..."""
    return codec if sums else f"{codec}, no sums"


def prune_command(src: Path, keep: float, by: str, seed: int) -> str:
    """The `gsc prune` command line a prune in the viewer stands for (its provenance)."""
    return shlex.join(
        ["gsc", "prune", src.name, "--keep", f"{keep:g}", "--by", by, "--seed", str(seed)]
    )


def share_command(src: Path, budget: Budget, options: ShareOptions) -> str:
    """The `gsc share` command line a share in the viewer stands for (its provenance: recorded
    in the file, so the preview's bytes are those written). Its strategy, codec, sums and seed:
    the viewer's shares take `gsc share`'s other settings as they are by default."""
    o = options
    words = [
        "gsc",
        "share",
        src.name,
        "--budget",
        str(budget),
        "--strategy",
        o.strategy,
        "--codec",
        o.codec,
        "--seed",
        str(o.seed),
    ]
    return shlex.join([*words, *([] if o.sums else ["--no-sums"])])


def kept_by_prune(gaussians: GaussianMap, keep: float, by: str, seed: int) -> np.ndarray:
    """[N] bool: the Gaussians `gsc prune --keep KEEP --by BY` keeps."""
    mask = np.zeros(len(gaussians), bool)
    mask[select_top(gaussians, keep, by, seed)[1]] = True
    return mask


@dataclass(frozen=True)
class SharePreview:
    """What `gsc share --budget B` would send.

    Attributes:
        budget: the budget.
        codec, sums: how it is sent.
        kept: [N] bool, the Gaussians it sends.
        file_bytes: bytes of the share file.
        sizes: bytes of the file of the same Gaussians in each of `SHARE_CODECS` (by label).
        shared: the Gaussians sent, as selected (before encoding).
    """

    budget: Budget
    codec: str
    sums: bool
    kept: np.ndarray
    file_bytes: int
    sizes: dict[str, int]
    shared: GaussianMap

    @property
    def count(self) -> int:
        """How many Gaussians the share holds."""
        return len(self.shared)


def preview_share(
    src: Path, source: tuple[GaussianMap, LogMetadata], budget: Budget, options: ShareOptions
) -> SharePreview:
    """The share `gsc share --budget BUDGET` with `options` would cut of the map `source` (of
    `src`): the count its byte search finds, and the size of that share in every codec.

    Raises:
        BudgetError: the budget holds no Gaussian, or the map has no such scores.
    """

    def cut(codec: str, sums: bool) -> ShareCut:
        how = replace(options, codec=codec, sums=sums)
        return ShareCut(src, budget, how, command=share_command(src, budget, how), source=source)

    codec, sums = options.codec, options.sums
    chosen = cut(codec, sums)
    count = chosen.budget.count(len(chosen.full), chosen.size)
    data, shared, _results = chosen.file(count)
    sizes = {
        codec_label(c, s): len(data) if (c, s) == (codec, sums) else cut(c, s).size(count)
        for c, s in SHARE_CODECS
    }
    kept = np.isin(source[0].ids, shared.ids)
    return SharePreview(budget, codec, sums, kept, len(data), sizes, shared)


def write_prune(
    src: Path,
    source: tuple[GaussianMap, LogMetadata],
    is_log: bool,
    dst: Path,
    keep: float,
    by: str,
    seed: int,
) -> dict[str, Any]:
    """Write the prune of `src` as `gsc prune` does (a log; for a map file, the kept Gaussians
    as a map file named by `dst`'s suffix)."""
    command = prune_command(src, keep, by, seed)
    if is_log:
        return prune_log(src, dst, keep, by=by, seed=seed, command=command)
    check_output(dst, [src], False, dst.suffix.lower() or ".ply")
    kept, _ = select_top(source[0], keep, by, seed)
    write_map_file(kept, dst, inputs=(src,))
    return {"output": str(dst), "kept": len(kept), "total": len(source[0])}


def write_share(
    src: Path,
    source: tuple[GaussianMap, LogMetadata],
    dst: Path,
    budget: Budget,
    options: ShareOptions,
) -> dict[str, Any]:
    """Write the share of `src` as `gsc share` does (`share_log`)."""
    command = share_command(src, budget, options)
    return share_log(src, dst, budget, options, command=command, source=source)
