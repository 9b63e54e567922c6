"""The offline commands: import-ply, prune, share, export-ply, export-traj and info.

numpy + mcap only: nothing here imports torch or the SLAM code, so these commands start fast.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from functools import cached_property
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.errors import InputError, LogFormatError, OptionError
from gscompress.gaussians import GaussianMap
from gscompress.io.codec import (
    DEFAULT_CODEC,
    DEFAULT_SHARE_CODEC,
    SHARE_IDS,
    carries_ids,
    check_codec,
    get_codec,
)
from gscompress.io.compact import COMPACT_DEFAULTS, CompactOptions
from gscompress.io.files import check_output, sha256, write_bytes_atomic
from gscompress.io.keyframes import CarriedFrame, carried_messages, write_carried
from gscompress.io.map_files import map_suffix, read_map_file, write_map_file
from gscompress.io.mcap_log import (
    TOPIC_CALIBRATION,
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    TOPIC_POSE_GT,
    LogMetadata,
    LogReader,
    LogWriter,
    Snapshot,
    pointcloud_bytes,
    read_map,
)
from gscompress.io.ply import write_ply
from gscompress.io.trajectory import write_tum_trajectory
from gscompress.ops.budget import Budget, largest_count_within
from gscompress.ops.fold import Folding
from gscompress.ops.merge import transform_map
from gscompress.pipeline.logs import trajectory
from gscompress.pipeline.receiver import Request, budget_less_request, read_request, unseen_ids
from gscompress.selection import (
    check_ratio,
    keep_count,
    selection_scores,
    strategy_scores,
    top_index,
)

log = logging.getLogger(__name__)

QUANTILES = (0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0)


def recorded_topics(parent: LogMetadata) -> dict[str, Any]:
    """The `recording` entry of a log's results (the topics, pairing tolerance and ground truth
    its run read a recording with), for the results of a log derived from it, so that
    reopening their sequence takes the same topics; {} when it has none."""
    value = parent.results.get("recording")
    return {} if value is None else {"recording": value}


class MapRefiner(Protocol):
    """Refines a map on the frames of the log it came from
    (`gscompress.pipeline.refine.LogRefiner`, which needs torch: prune and share take one only
    when asked to refine)."""

    def __call__(
        self,
        gaussians: GaussianMap,
        rates: Any = None,
        teacher: GaussianMap | None = None,
        iters: int | None = None,
    ) -> tuple[GaussianMap, dict[str, Any]]:
        """The map refined (same Gaussians, same order) and the refinement's statistics;
        `teacher`, the map it was cut from, is also rendered between the keyframes and refined
        on (`gscompress.pipeline.refine.PSEUDO_VIEWS`); `iters` (None: its own) iterations."""
        ...

    def record(self) -> dict[str, Any]:
        """What a provenance step records of the refinement."""
        ...

    @property
    def anisotropic(self) -> bool:
        """Whether it refines three scales and a rotation per Gaussian (`cut_pool`)."""
        ...


def import_ply(
    src: str | Path, dst: str | Path, *, command: str = "", force: bool = False
) -> dict[str, Any]:
    """Turn a map file of any 3DGS tool (PLY, compressed PLY or SPZ) into a one-snapshot
    gscompress log."""
    check_output(dst, [src], force, ".mcap")
    gaussians = read_map_file(src)
    meta = LogMetadata().derive({"name": "import-ply"}, src, command)
    return _map_log(gaussians, dst, meta, src, force=force)


def _map_log(
    gaussians: GaussianMap,
    dst: str | Path,
    meta: LogMetadata,
    src: str | Path,
    results: dict[str, Any] | None = None,
    *,
    force: bool = False,
) -> dict[str, Any]:
    """A one-snapshot log of a map that came from `src` (`meta`: its metadata)."""
    meta.results = {"gaussians": len(gaussians), "scored": gaussians.has_importance,
                    **(results or {})}  # fmt: skip
    with LogWriter(dst, meta, inputs=[src], force=force) as out:
        out.write_gaussians(gaussians, 0)
    return {"output": str(dst), **meta.results}


REFERENCE_FORMATS = (DEFAULT_CODEC, "spz", "sog")
"""The formats `format_share` sends a whole map in: the points of the field on a
rate-distortion plot."""


def format_share(
    src: str | Path, dst: str | Path, fmt: str, *, command: str = "", force: bool = False
) -> dict[str, Any]:
    """A log's whole map as it would cross the link in `fmt`, as a share log the receiver merges
    like any other, with the `selected` Gaussians and the bytes that crossed (`file_bytes`).

    "fp32": `share_log` of every Gaussian in the fp32 codec, not folded (`bytes` its map
    message, `file_bytes` the share file). "spz" (our writer, SPZ version 4) and "sog" (written
    by splat-transform, `gscompress.io.sog.write_sog`): the file in that format (`bytes` and
    `file_bytes` its size), read back as `gsc import-ply` reads it. Neither keeps ids or PWAS
    sums: the ids are 0..N-1 and the evidence a merge weighs (alpha x T sums) is zero.

    Raises:
        InputError: an unknown format. MissingDependencyError: "sog" without splat-transform.
    """
    if fmt not in REFERENCE_FORMATS:
        raise InputError(f"unknown format {fmt!r}; choose from {', '.join(REFERENCE_FORMATS)}")
    if fmt == DEFAULT_CODEC:
        got = share_log(src, dst, "1", codec=fmt, fold_dropped=False, command=command,
                        force=force)  # fmt: skip
        return {**got, "format": fmt}
    import tempfile

    from gscompress.io.sog import write_sog
    from gscompress.io.spz import write_spz

    check_output(dst, [src], force, ".mcap")
    with LogReader(src) as log_in:
        whole, parent = log_in.read_map(), log_in.metadata
    with tempfile.TemporaryDirectory() as tmp:
        file = Path(tmp) / f"map.{fmt}"
        if fmt == "spz":
            write_spz(whole, file)
        else:
            write_sog(whole, file)
        size = file.stat().st_size
        back = read_map_file(file)
    results = {"format": fmt, "selected": len(back), "bytes": size, "file_bytes": size}
    results |= recorded_topics(parent)
    # (the map is in the sender's world frame, which the log records as a share's does)
    meta = parent.derive({"name": "format-share", "format": fmt}, src, command)
    meta.config = {}  # (as a share's)
    return _map_log(back, dst, meta, src, results, force=force)


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
    fold_dropped: bool = True,
    command: str = "",
    force: bool = False,
) -> dict[str, Any]:
    """Keep the `keep` fraction of a log's map with the highest `by` scores (`cut_map`: with
    `fold_dropped`, what is dropped is folded into the kept Gaussians).

    The last `/gaussians` snapshot is replaced by its pruned version (same log time), stored in
    `codec` (None: the codec of the map it replaces); every other message, earlier snapshots
    included, passes through unchanged (with `map_only`, only the calibration does: see
    `rewrite_map`). `refine` (a `gscompress.pipeline.refine.LogRefiner`) refines the kept
    Gaussians before they are written; it never adds or drops one.
    """
    check_ratio(keep, "--keep")

    def prune(full: GaussianMap) -> tuple[GaussianMap, dict[str, Any]]:
        scores = selection_scores(full, by, seed)
        kept = cut_map(cut_pool(full, refine), keep_count(len(full), keep), scores, fold_dropped)
        return refined(kept, {"kept": len(kept), "total": len(full), "fold": fold_dropped},
                       refine, teacher=full)  # fmt: skip

    operation: dict[str, Any] = {"name": "prune", "keep": keep, "by": by, "seed": seed,
                                 "fold": fold_dropped}  # fmt: skip
    if refine is not None:
        operation["refine"] = refine.record()
    if map_only:
        operation["map_only"] = True
    return rewrite_map(src, dst, operation, prune, codec=codec, options=options,
                       command=command, force=force, map_only=map_only)  # fmt: skip


def cut_pool(full: GaussianMap, refine: MapRefiner | None) -> GaussianMap:
    """The map a prune or a share cuts from: `full`, with three scales a Gaussian when `refine`
    refines them so (`RefineOptions.anisotropic`): the fold then keeps each group's covariance
    (`gscompress.ops.fold`) instead of the isotropic Gaussian of its trace."""
    return full.as_anisotropic() if refine is not None and refine.anisotropic else full


def cut_map(
    full: GaussianMap,
    count: int,
    scores: np.ndarray,
    fold_dropped: bool,
    first: np.ndarray | None = None,
    folding: Folding | None = None,
) -> GaussianMap:
    """The `count` Gaussians of `full` with the highest `scores` (a strategy's, from
    `selection.selection_scores`: spread over space there if asked), each with the dropped ones
    near it folded into it when `fold_dropped` (`gscompress.ops.fold`; same Gaussians, ids and
    order either way). What `gsc prune` keeps and `gsc share` sends. `first` ([N] bool) ranks
    the Gaussians it marks above all the others (a receiver-aware share). `folding`, the
    `Folding` of `full`, folds it when given: a caller that cuts many counts of one map passes
    the same one each time."""
    index = top_index(full, count, scores, first)
    if not fold_dropped:
        return full.select(index)
    return (folding or Folding(full)).fold(index)


def refined(
    gaussians: GaussianMap,
    results: dict[str, Any],
    refine: MapRefiner | None,
    teacher: GaussianMap | None = None,
) -> tuple[GaussianMap, dict[str, Any]]:
    """`gaussians` through `refine` when there is one (with `teacher`, the map they were cut
    from), its statistics added to `results` as `refine_*`."""
    if refine is None:
        return gaussians, results
    gaussians, stats = refine(gaussians, teacher=teacher)
    return gaussians, {**results, **{f"refine_{k}": v for k, v in stats.items()}}


def rewrite_map(
    src: str | Path,
    dst: str | Path,
    operation: dict[str, Any],
    transform: Callable[[GaussianMap], tuple[GaussianMap, dict[str, Any]]],
    *,
    codec: str | None = None,
    options: CompactOptions = COMPACT_DEFAULTS,
    command: str = "",
    force: bool = False,
    map_only: bool = False,
) -> dict[str, Any]:
    """Copy a log, replacing its map (the last snapshot) by `transform(map)`.

    Every other message passes through unchanged; with `map_only`, only the calibration does
    (no earlier snapshots, poses, stats or transforms: the file is as small as the map). The
    output's provenance gains `operation` and its results are what `transform` returns beside
    the new map. The new map is stored in `codec` (with `options` for compact), or None: in the
    codec of the one it replaces (an fp16 share stays fp16). The parent's recorded topics
    (`recorded_topics`) are carried into the results.
    """
    if codec is not None:
        check_codec(codec)
    check_output(dst, [src], force, ".mcap")
    with LogReader(src) as log_in:
        last = log_in.require_snapshots() - 1
        meta = log_in.metadata.derive(operation, src, command)
        inherited = recorded_topics(log_in.metadata)
        with LogWriter(dst, meta, inputs=[src], force=force) as out:
            snapshot = 0
            for schema, channel, message in log_in.iter_messages():
                if channel.topic != TOPIC_GAUSSIANS:
                    if not map_only or channel.topic == TOPIC_CALIBRATION:
                        out.copy_message(schema, channel, message)
                    continue
                if snapshot == last:
                    stored = log_in.decode_snapshot(schema, message)
                    new_map, results = transform(stored.gaussians)
                    meta.results = {**results, **inherited}
                    chosen = codec or stored.codec
                    meta.results["codec"] = chosen
                    out.write_gaussians(new_map, message.log_time, chosen, options)
                elif not map_only:
                    out.copy_message(schema, channel, message)
                snapshot += 1
    return {"output": str(dst), **meta.results}


def smallest_share_bytes(codec: str = DEFAULT_SHARE_CODEC) -> int:
    """Bytes of the smallest possible share file in `codec`: one Gaussian and a metadata record
    without provenance (every share of a log is larger, so a smaller budget holds nothing)."""
    one = GaussianMap.new(
        means=np.zeros((1, 3)),
        log_scales=np.zeros((1, 1)),
        quats=np.array([[1.0, 0.0, 0.0, 0.0]]),
        opacity_logits=np.zeros(1),
        sh_dc=np.zeros((1, 3)),
    )
    with LogWriter(None, LogMetadata()) as out:
        out.write_gaussians(one, 0, codec)
    return len(out.data)


PROBE_ITERS = 100
"""A refined share under a byte budget first refines its cut this many iterations to learn how
the refined values compress (`ShareCut.refined`). Tabletop's map at 10%bytes, refined 1000
iterations with three scales a Gaussian: sized before the refinement, 4891 Gaussians were
refined, 4350 of them fit afterwards, and with the rest folded in the share scored 25.87 dB
off the keyframes, against 26.88 for the isotropic share; with the probe, 4355 are refined
and sent: 27.22 dB (docs/prune-refine.md)."""


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
        *,
        strategy: str = "pwas",
        codec: str = DEFAULT_SHARE_CODEC,
        sums: bool = True,
        ids: bool = SHARE_IDS,
        seed: int = 0,
        fold_dropped: bool = True,
        refine: MapRefiner | None = None,
        solve: dict[str, Any] | None = None,
        command: str = "",
        source: tuple[GaussianMap, LogMetadata] | None = None,
        align: tuple[np.ndarray, dict[str, Any]] | None = None,
        carry: tuple[list[CarriedFrame], Intrinsics] | None = None,
        receiver: Request | None = None,
        device: str = "auto",
        spread: bool = False,
    ):
        self.src = Path(src)
        self.carry = carry
        self.fold, self.spread = fold_dropped, spread
        self.strategy, self.codec, self.sums, self.seed = strategy, check_codec(codec), sums, seed
        self.ids = carries_ids(codec, ids)
        if source is None:
            with LogReader(src) as log_in:
                source = log_in.read_map(), log_in.metadata
        self.full, meta = source
        self._recorded = recorded_topics(meta)
        fp32_bytes = pointcloud_bytes(self.full, DEFAULT_CODEC)(len(self.full))
        self.budget = budget = budget.resolve(fp32_bytes)
        operation = {"name": "share", **budget.record(), "strategy": strategy, "seed": seed}
        operation.update(codec=codec, sums=sums, ids=self.ids, fold=fold_dropped)
        if spread:
            operation["spread"] = True
        self.first_ids: np.ndarray | None = None  # what the receiver has not seen (sent first)
        self.receiver: dict[str, Any] = {}
        if receiver is not None:
            if align is None and receiver.world_frame != meta.world_frame:
                raise InputError(
                    f"{receiver.source} is in the world frame {receiver.world_frame!r}, {self.src}"
                    f" in {meta.world_frame!r}: add --align-to {receiver.source} to find the "
                    "transform between them"
                )
            self.budget = budget_less_request(budget, receiver)
            self.first_ids = unseen_ids(self.full, receiver, None if align is None else align[0],
                                        device=device)  # fmt: skip
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
        self._sizes: dict[int, int] = {}
        self._last: tuple[int, tuple[bytes, GaussianMap, dict[str, Any]]] | None = None
        self._take_from(self.full)
        if refine is not None and refine.anisotropic and not self._holds_whole_map():
            self._take_from(cut_pool(self.full, refine))  # (else shaping only leaves some out)

    def _holds_whole_map(self) -> bool:
        """Whether a byte budget holds the whole map as it is. A refined share is then not
        shaped (`cut_pool`): tabletop's map at 20%bytes, refined 1000 iterations, scored 27.41
        dB off the keyframes whole and isotropic, 27.31 shaped (9,051 of its 11,052 Gaussians
        fit), 27.49 not refined (docs/prune-refine.md)."""
        limit = self.budget.budget_bytes
        return limit is not None and self.size(len(self.pool)) <= limit

    def _take_from(self, pool: GaussianMap) -> None:
        """Take the K best from `pool`: its ranking and the receiver's preference are computed
        here once, not for every count a byte budget tries."""
        self._sizes, self._last = {}, None
        self.pool = pool
        self._scores = selection_scores(pool, self.strategy, self.seed, self.spread)
        self._first = None if self.first_ids is None else np.isin(pool.ids, self.first_ids)
        self._folding = Folding(pool) if self.fold else None  # (one for every count tried)

    def _cut(self, count: int) -> GaussianMap:
        return cut_map(self.pool, count, self._scores, self.fold, self._first, self._folding)

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
                "source": self.src.name,
                "strategy": self.strategy,
                **self.budget.record(),
                "codec": self.codec,
                "sums": self.sums,
                "ids": self.ids,
                "fold": self.fold,
                **({"spread": True} if self.spread else {}),
                "selected": len(shared),
                "total": len(self.full),
                **self.receiver,
                **self.extra,
                **self._recorded,
            }
            with LogWriter(None, meta) as out:
                options = CompactOptions(sums=self.sums, ids=self.ids)
                meta.results["bytes"] = out.write_gaussians(shared, 0, self.codec, options)
                if self.carry is not None:
                    frames, camera = self._carried
                    meta.results["keyframes"] = len(frames)
                    meta.results["keyframe_bytes"] = write_carried(
                        out, frames, camera, self._carried_messages
                    )
            self._last = (count, (out.data, shared, dict(meta.results)))
            self._sizes[count] = len(out.data)
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
        """Bytes of the share file of the `count` best Gaussians."""
        return self._sizes[count] if count in self._sizes else len(self.file(count)[0])


def share_log(
    src: str | Path,
    dst: str | Path,
    budget: str | float | Budget,
    *,
    strategy: str = "pwas",
    codec: str = DEFAULT_SHARE_CODEC,
    sums: bool = True,
    ids: bool = SHARE_IDS,
    seed: int = 0,
    fold_dropped: bool = True,
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
    spread: bool = False,
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
        strategy: what to rank Gaussians by (`Strategy`).
        codec: how the map is stored (`gscompress.io.codec.CODECS`): compact (the default, about
            10-20 bytes per Gaussian), fp16 or fp32 (a foxglove.PointCloud Foxglove draws).
        sums: send the PWAS sums (a receiver that keeps accumulating needs them); without them
            a compact share sends the score alone (fp32 and fp16 always send the sums).
        ids: send each Gaussian's id (`SHARE_IDS`: not unless asked); without them a compact
            share is about 2 bytes a Gaussian smaller and the receiver numbers them 0..N-1 (fp32
            and fp16 always send them).
        seed: seed of the random strategy.
        fold_dropped: fold what the share leaves out into the Gaussians it sends (`cut_map`).
        ply: also write the share as a float32 3DGS PLY (the decoded values).
        refine: refines the selected Gaussians before they are sent (a
            `gscompress.pipeline.refine.LogRefiner` on the sender's frames); a byte budget
            still bounds the file of the refined values (the last few may then be left out).
        solve: the byte-budget solver's record of how it chose the codec (for the provenance;
            see `gscompress.pipeline.solve`).
        align_to: a log of the receiving agent whose world frame differs: the share is cut
            in that log's frame, the transform found by `gsc align`'s aligner (recorded in the
            provenance with its overlap and residual); the receiver then merges it as is.
        command: command line for the provenance record.
        force: overwrite existing outputs.
        source: the map and metadata of `src` when they are already read (a map file's map,
            with `LogMetadata()`: see `ShareCut`).
        carry: keyframes of the sender to send along, and their camera
            (`gscompress.pipeline.refine.carried_keyframes`; `gscompress.io.keyframes`): a
            byte budget counts their bytes too, leaving fewer Gaussians.
        receiver: the receiving agent's log: the Gaussians its views do not draw are sent
            first (`gscompress.pipeline.receiver`; needs torch, rendered on `device`); a byte
            budget counts its request's bytes too. In its own world frame, which must be the
            map's unless `align_to` gives the transform.
        spread: send the best of distinct places first (`selection.spread_ranks`): the
            strategy's order, spread over space.
        progress: called with how many cuts a byte budget has tried so far (each a fold and
            an encoding of the whole share), as its search goes (0: it starts).

    Raises:
        InputError: bad budget, codec or strategy (OptionError: --ply equal to the MCAP
            output).
        BudgetError: the budget holds no Gaussian.
        MapError: at fp16, a selected value beyond the float16 range.
    """
    budget = Budget.parse(budget)
    check_codec(codec)
    outputs = [(dst, ".mcap")] if ply is None else [(dst, ".mcap"), (ply, ".ply")]
    if ply is not None and Path(ply).resolve() == Path(dst).resolve():
        raise OptionError("--ply must differ from the MCAP output")
    inputs = [p for p in (src, align_to, receiver) if p is not None]
    for path, suffix in outputs:
        check_output(path, inputs, force, suffix)
    align = None
    if align_to is not None:
        from gscompress.pipeline.align import share_alignment

        align = share_alignment(src, align_to)
    cut = ShareCut(src, budget, strategy=strategy, codec=codec, sums=sums, ids=ids, seed=seed,
                   fold_dropped=fold_dropped, refine=refine, solve=solve, command=command,
                   source=source, align=align, carry=carry,
                   receiver=None if receiver is None else read_request(receiver),
                   device=device, spread=spread)  # fmt: skip
    searched = cut.budget.budget_bytes is not None
    count = cut.budget.count(len(cut.full), _counted(cut.size, progress) if searched else cut.size)
    if refine is not None:
        count = cut.refined(count, refine)
    data, shared, results = cut.file(count)
    limit = cut.budget.budget_bytes
    if limit is not None and len(data) > limit:
        raise AssertionError(f"share of {len(data)} B exceeds {limit} B")
    results["file_bytes"] = len(data)
    write_bytes_atomic(dst, data)
    if ply is not None:
        try:  # the receiver's values: what the share decodes to
            received = shared if get_codec(codec).lossless else read_map(dst)
            write_ply(received, ply, inputs=(src,), force=force)
        except BaseException:  # a share is written whole or not at all
            Path(dst).unlink(missing_ok=True)
            raise
    return {"output": str(dst), "ply": None if ply is None else str(ply), **results}


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


def export_ply(
    src: str | Path,
    dst: str | Path,
    *,
    snapshot: int = -1,
    importance: bool = True,
    force: bool = False,
) -> dict[str, Any]:
    """Write one snapshot of a log (default the last, "the map") as a 3DGS PLY file, or as SPZ
    when `dst` ends in `.spz` (without scores or ids: SPZ has no place for them)."""
    check_output(dst, [src], force, map_suffix(dst))
    with LogReader(src) as log_in:
        gaussians = log_in.read_map(snapshot)
        index = snapshot % log_in.snapshot_count  # read_map refused one out of range
    write_map_file(gaussians, dst, importance=importance, inputs=(src,), force=force)
    return {"output": str(dst), "gaussians": len(gaussians), "snapshot": index}


def export_trajectory(
    src: str | Path, dst: str | Path, *, ground_truth: bool = False, force: bool = False
) -> dict[str, Any]:
    """Write a log's estimated poses (or, with `ground_truth`, its `/camera/pose_gt`) as a TUM
    trajectory, stamped with the frames' timestamps, for evo and other tools.

    Raises:
        LogFormatError: the log has no such poses (not a SLAM log, or no ground truth).
    """
    topic = TOPIC_POSE_GT if ground_truth else TOPIC_POSE
    check_output(dst, [src], force, ".txt")
    with LogReader(src) as log_in:
        if ground_truth:
            stamps_ns, poses = log_in.read_poses(topic)
            source = "ground truth"
        else:
            found = trajectory(log_in)
            stamps_ns, poses, source = found.times_ns, found.T_world_cam, found.source
    if len(poses) == 0:
        what = "ground-truth poses" if ground_truth else "estimated poses (not a SLAM log?)"
        raise LogFormatError(f"{src} has no {topic} messages: no {what}")
    refined = "" if source in ("tracked", "ground truth") else f" ({source})"
    name = "ground truth" if ground_truth else f"estimated trajectory{refined}"
    write_tum_trajectory(dst, stamps_ns / 1e9, poses, [f"{name} of {Path(src).name}"])
    return {"output": str(dst), "poses": len(poses), "topic": topic, "trajectory": source}


def log_info(path: str | Path, *, histogram_bins: int = 10) -> dict[str, Any]:
    """Summarise a log: channels, snapshots, the map, its scores, bytes and provenance.

    `map.bytes` is the serialized `/gaussians` message of the map, `map.bytes_per_gaussian`
    that per Gaussian and `map.codec` how it is stored (fp32, fp16 or compact); each snapshot
    says the same. `file_bytes` is the whole file (what a byte budget bounds for a share).
    """
    path = Path(path)
    with LogReader(path) as log_in:
        channels = [
            {"topic": c.topic, "schema": c.schema, "encoding": c.encoding, "messages": c.messages}
            for c in log_in.channels
        ]
        snapshots: list[dict[str, Any]] = []
        final: Snapshot | None = None
        for schema, _channel, message in log_in.iter_messages([TOPIC_GAUSSIANS]):
            final = log_in.decode_snapshot(schema, message)
            snapshots.append(
                {
                    "log_time_ns": message.log_time,
                    "gaussians": len(final.gaussians),
                    "codec": final.codec,
                    "bytes": final.message_bytes,
                }
            )
        meta = log_in.metadata
    info: dict[str, Any] = {
        "path": str(path),
        "file_bytes": path.stat().st_size,
        "sha256": sha256(path),
        "profile_version": meta.profile_version,
        "tool_version": meta.tool_version,
        "command": meta.command,
        "sequence": meta.sequence,
        "frames": meta.frames,
        "world_frame": meta.world_frame,
        "channels": channels,
        "snapshots": snapshots,
        "provenance": meta.provenance,
        "results": meta.results,
    }
    if final is not None:
        info["map"] = map_summary(final.gaussians, histogram_bins)
        info["map"]["codec"] = final.codec
        info["map"]["bytes"] = final.message_bytes
        info["map"]["bytes_per_gaussian"] = final.bytes_per_gaussian
    return info


def map_summary(gaussians: GaussianMap, histogram_bins: int = 10) -> dict[str, Any]:
    """Counts, layout, bounds and score statistics of a map (JSON-ready)."""
    summary: dict[str, Any] = {
        "gaussians": len(gaussians),
        "isotropic": gaussians.isotropic,
        "sh_degree": gaussians.sh_degree,
        "has_importance": gaussians.has_importance,
    }
    if len(gaussians):
        summary["bounds_min"] = gaussians.means.min(axis=0).tolist()
        summary["bounds_max"] = gaussians.means.max(axis=0).tolist()
        summary["opacity_mean"] = float(gaussians.opacities().mean())
    if gaussians.has_importance and len(gaussians):
        scores = strategy_scores(gaussians, "pwas")
        summary["importance_quantiles"] = {
            f"q{round(q * 100):02d}": float(v)
            for q, v in zip(QUANTILES, np.quantile(scores, QUANTILES), strict=True)
        }
        counts, edges = np.histogram(scores, bins=histogram_bins)
        summary["importance_histogram"] = {"counts": counts.tolist(), "edges": edges.tolist()}
        # scores span decades (a few Gaussians dominate), so the linear bins put nearly all
        # in the first; the log-spaced ones show the shape (zero scores counted apart)
        positive = scores[scores > 0]
        counts, edges = np.histogram(positive, bins=log_edges(positive, histogram_bins))
        summary["importance_histogram_log"] = {
            "counts": counts.tolist(),
            "edges": edges.tolist(),
            "zeros": int(len(scores) - len(positive)),
        }
        summary["scored"] = int(np.count_nonzero(gaussians.importance_weight > 0))
    return summary


def log_edges(positive: np.ndarray, bins: int) -> np.ndarray:
    """`bins` + 1 log-spaced histogram edges from the smallest to the largest of these positive
    scores (a span of 1% when they are all equal, [1e-6, 1] when there are none)."""
    low, high = (float(positive.min()), float(positive.max())) if len(positive) else (1e-6, 1.0)
    high = max(high, low * 1.01)
    edges = np.logspace(np.log10(low), np.log10(high), bins + 1)
    edges[[0, -1]] = low, high  # exactly: 10 ** log10(x) may round off x and leave it out
    return edges
