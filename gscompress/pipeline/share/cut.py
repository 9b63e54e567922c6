"""The share files of a log's map for one budget, strategy and codec (`ShareCut`): the file
holding the K best Gaussians, written in memory, for any K (what a byte budget searches over)."""

from __future__ import annotations

from dataclasses import replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.errors import InputError
from gscompress.gaussians import GaussianMap
from gscompress.io.codec import DEFAULT_CODEC, DEFAULT_SHARE_CODEC
from gscompress.io.compact import CompactOptions
from gscompress.io.files import safe_text
from gscompress.io.keyframes import CarriedFrame, carried_messages, write_carried
from gscompress.io.mcap_log import LogMetadata, LogReader, LogWriter, pointcloud_bytes
from gscompress.ops.budget import Budget, largest_count_within
from gscompress.ops.fold import Folding, cut_map, cut_pool
from gscompress.ops.merge import transform_map
from gscompress.ops.refine import MapRefiner, refined
from gscompress.pipeline.logs import recorded_topics
from gscompress.pipeline.share.options import ShareOptions
from gscompress.pipeline.share.receiver import (
    Request,
    budget_less_request,
    unseen_ids,
)
from gscompress.selection import Ranking, selection_scores

RECORDED_TEXT_BYTES = 256
"""What a share counts for the text it records of local paths (its command line and the names
of the files it was made from), whatever their length, so that a budget gives the same share
from any folder and under any file name. A longer command line is recorded shortened to fit;
only names of over a hundred characters or so can still make a share smaller."""

ELLIPSIS = "\u2026"

NAME_KEYS = frozenset({"parent", "source", "for", "target"})
"""The keys under which a share's provenance step and results record a file's name."""

PROBE_ITERS = 100
"""A refined share under a byte budget first refines its cut this many iterations to learn how
the refined values compress (`ShareCut.refined`). Sized before the refinement, a shaped share
no longer fits once refined, and folding the Gaussians left out into the refined map costs more
than the shape gave (below the isotropic share); sized by the probe, the Gaussians refined are
the ones sent, and the share beats the isotropic one (measured on tabletop in
docs/prune-refine.md, "Shaped refinement (the default)")."""


DEFAULTS = ShareOptions()
"""`gsc share`'s settings unless asked otherwise."""


class ShareCut:
    """The share files of a log's map for one budget, strategy and codec: the file holding the
    K best Gaussians, written in memory, for any K (what a byte budget searches over).

    `source` gives the map and metadata of `src` when they are already read (the viewer cuts
    many shares of one map; a map file has no metadata: `LogMetadata()`).

    Attributes:
        full: the map shared from (the log's last snapshot).
    """

    def __init__(
        self,
        src: str | Path,
        budget: Budget,
        options: ShareOptions = DEFAULTS,
        *,
        refine: MapRefiner | None = None,
        solve: dict[str, Any] | None = None,
        command: str = "",
        source: tuple[GaussianMap, LogMetadata] | None = None,
        align: tuple[np.ndarray, dict[str, Any]] | None = None,
        carry: tuple[list[CarriedFrame], Intrinsics] | None = None,
        receiver: Request | None = None,
        device: str = "auto",
    ):
        options.check()
        self.src = Path(src)
        self.carry = carry
        self.options = options
        if source is None:
            with LogReader(src) as log_in:
                source = log_in.read_map(), log_in.metadata
        self.full, meta = source
        self._recorded = recorded_topics(meta)
        fp32_bytes = pointcloud_bytes(self.full, DEFAULT_CODEC)(len(self.full))
        self.budget = budget = budget.resolve(fp32_bytes)
        operation = options.provenance(budget)
        self.first_ids: np.ndarray | None = None  # what the receiver has not seen (sent first)
        self.receiver: dict[str, Any] = {}
        if receiver is not None:
            if align is None and receiver.world_frame != meta.world_frame:
                raise InputError(
                    f"{receiver.source} is in the world frame {receiver.world_frame!r}, {self.src}"
                    f" in {meta.world_frame!r}: add `align_to` {receiver.source} to find the "
                    "transform between them",
                    options=("align_to",),
                )
            self.budget = budget_less_request(budget, receiver)
            self.first_ids = unseen_ids(
                self.full, receiver, None if align is None else align[0], device=device
            )
            self.receiver = {**receiver.record(), "unseen": len(self.first_ids)}
            operation["for"] = self.receiver
        if refine is not None:
            operation["refine"] = refine.record()
        if solve is not None:
            operation["solve"] = solve
        self.T_target_source = None if align is None else align[0]
        if align is not None:
            operation["align_to"] = align[1]
        self._meta = meta.derive(operation, src, command)
        self._meta.config = {}  # bytes on the link: the receiver maps with its own config
        if align is not None:  # the share is expressed in the target's frame
            self._meta.world_frame = align[1]["target_world_frame"]
        self.extra: dict[str, Any] = {}  # further results (a refinement's)
        self._sizes: dict[int, int] = {}  # counted: the path text at RECORDED_TEXT_BYTES
        self._path_bytes: int | None = None
        self._last: tuple[int, tuple[bytes, GaussianMap, dict[str, Any]]] | None = None
        self._take_from(self.full)
        if refine is not None and refine.anisotropic and not self._holds_whole_map():
            self._take_from(cut_pool(self.full, refine))  # (else shaping only leaves some out)

    def _holds_whole_map(self) -> bool:
        """Whether a byte budget holds the whole map as it is. A refined share is then not
        shaped (`cut_pool`): shaping would only leave Gaussians out, and on tabletop the whole
        map refined isotropic scored higher than the shaped share and the whole map unrefined
        higher still (docs/prune-refine.md, "Shaped refinement (the default)")."""
        limit = self.budget.budget_bytes
        return limit is not None and self.size(len(self.pool)) <= limit

    def _take_from(self, pool: GaussianMap) -> None:
        """Take the K best from `pool`: its ranking and the receiver's preference are computed
        here once, not for every count a byte budget tries."""
        self._sizes, self._last = {}, None
        self.pool = pool
        o = self.options
        self._scores = selection_scores(pool, o.strategy, o.seed, o.spread)
        self._first = None if self.first_ids is None else np.isin(pool.ids, self.first_ids)
        self._folding = Folding(pool) if o.fold else None  # (one for every count tried)
        self._ranking = Ranking(pool, self._scores, self._first)  # (likewise)

    def _cut(self, count: int) -> GaussianMap:
        return cut_map(
            self.pool,
            count,
            self._scores,
            self.options.fold,
            self._first,
            self._folding,
            self._ranking,
        )

    def refined(self, count: int, refine: MapRefiner) -> int:
        """Refine the share of the `count` best Gaussians and take later shares from it; the
        count that then fits (the refined values may compress less well than the first ones:
        the budget still holds).

        Under a byte budget the cut is first refined for `PROBE_ITERS` iterations to learn how
        its refined values compress, and the count that then fits is refined in full, so that
        what is sent is what was refined; should the refined values still not fit, the last
        few are left out (and folded in) after the refinement."""
        origin = self.pool
        if self.budget.budget_bytes is not None:
            probe, _ = refine(self._cut(count), teacher=origin, iters=PROBE_ITERS)
            self._take_from(probe)
            count = self._largest_count(count)
            self._take_from(origin)
        pool, self.extra = refined(self._cut(count), {}, refine, teacher=origin)
        self._take_from(pool)
        return count if self.budget.budget_bytes is None else self._largest_count(count)

    def _largest_count(self, available: int) -> int:
        """The most of the pool's first `available` Gaussians whose share fits the budget."""
        assert self.budget.budget_bytes is not None
        return largest_count_within(self.budget.budget_bytes, available, self.size)

    def file(self, count: int) -> tuple[bytes, GaussianMap, dict[str, Any]]:
        """The share file of the `count` best Gaussians: its bytes, its map (as selected, before
        encoding) and the results its metadata records. (Only the last one is kept.)"""
        if self._last is None or self._last[0] != count:
            shared = self._cut(count)
            if self.T_target_source is not None:  # (the sender's frames refine, before this)
                shared = transform_map(shared, self.T_target_source)
            meta = self._meta
            meta.results = {
                **self.options.results(self.src.name, self.budget),
                "selected": len(shared),
                "total": len(self.full),
                **self.receiver,
                **self.extra,
                **self._recorded,
            }
            if self._path_bytes is None:  # (the same for every count)
                self._path_bytes = _fit_path_text(meta)
            with LogWriter(None, meta) as out:
                o = self.options
                columns = CompactOptions(sums=o.sums, ids=o.sends_ids)
                meta.results["bytes"] = out.write_gaussians(shared, 0, o.codec, columns)
                if self.carry is not None:
                    frames, camera = self._carried
                    meta.results["keyframes"] = len(frames)
                    meta.results["keyframe_bytes"] = write_carried(
                        out, frames, camera, self._carried_messages
                    )
            self._last = (count, (out.data, shared, dict(meta.results)))
            self._sizes[count] = len(out.data) + max(RECORDED_TEXT_BYTES - self._path_bytes, 0)
        return self._last[1]

    @cached_property
    def _carried(self) -> tuple[list[CarriedFrame], Intrinsics]:
        """The keyframes carried (in the share's frame) and their camera."""
        assert self.carry is not None
        frames, camera = self.carry
        if self.T_target_source is not None:
            frames = [f.moved(self.T_target_source) for f in frames]
        return frames, camera

    @cached_property
    def _carried_messages(self) -> list[tuple[str, Any, int]]:
        """Their messages, encoded once for every count tried."""
        return carried_messages(self._carried[0])

    def size(self, count: int) -> int:
        """Bytes of the share file of the `count` best Gaussians, its path text counted at
        `RECORDED_TEXT_BYTES` (what a budget holds; the file is no larger)."""
        if count not in self._sizes:
            self.file(count)
        return self._sizes[count]


def _fit_path_text(meta: LogMetadata) -> int:
    """`path_text_bytes` of `meta`, its command line first shortened so that they fit in
    `RECORDED_TEXT_BYTES` where they can."""
    spent = path_text_bytes(meta)
    if spent > RECORDED_TEXT_BYTES and meta.command:
        meta.command = _shortened(meta.command, spent - RECORDED_TEXT_BYTES)
        spent = path_text_bytes(meta)
    return spent


def path_text_bytes(meta: LogMetadata) -> int:
    """The bytes a share's metadata record spends on local paths: its command line, and the
    names under `NAME_KEYS` in its last provenance step and its results."""
    blank = replace(
        meta,
        command="",
        provenance=[*meta.provenance[:-1], *map(_without_names, meta.provenance[-1:])],
        results=_without_names(meta.results),
    )
    return _record_bytes(meta) - _record_bytes(blank)


def _without_names(value: Any) -> Any:
    """A JSON value with every string under a key of `NAME_KEYS` emptied."""
    if isinstance(value, dict):
        return {
            k: "" if k in NAME_KEYS and isinstance(v, str) else _without_names(v)
            for k, v in value.items()
        }
    if isinstance(value, list):
        return [_without_names(v) for v in value]
    return value


def _record_bytes(meta: LogMetadata) -> int:
    """Bytes of the keys and values of `meta`'s MCAP metadata record (the rest of it, its
    lengths and name, has a fixed size)."""
    return sum(len(k.encode()) + len(v.encode()) for k, v in meta.to_record().items())


def _shortened(text: str, excess: int) -> str:
    """`text` (as the metadata record writes it) made at least `excess` bytes shorter, its end
    replaced by an ellipsis ("" when nothing of it would be left)."""
    data = safe_text(text).encode()
    keep = len(data) - excess - len(ELLIPSIS.encode())
    return data[:keep].decode(errors="ignore") + ELLIPSIS if keep > 0 else ""


def smallest_share_bytes(codec: str = DEFAULT_SHARE_CODEC) -> int:
    """Bytes of the smallest possible share in `codec`, as a budget counts it: one Gaussian, a
    metadata record without provenance and `RECORDED_TEXT_BYTES` (every share of a log is
    larger, so a smaller budget holds nothing)."""
    one = GaussianMap.new(
        means=np.zeros((1, 3)),
        log_scales=np.zeros((1, 1)),
        quats=np.array([[1.0, 0.0, 0.0, 0.0]]),
        opacity_logits=np.zeros(1),
        sh_dc=np.zeros((1, 3)),
    )
    with LogWriter(None, LogMetadata()) as out:
        out.write_gaussians(one, 0, codec)
    return len(out.data) + RECORDED_TEXT_BYTES
