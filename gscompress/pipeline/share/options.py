"""A share's settings (`ShareOptions`): what `gsc share`, the solver, the viewer's preview and the
experiment's share steps cut a map by, with their checks and the record a share keeps of them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gscompress.io.codec import DEFAULT_SHARE_CODEC, SHARE_IDS, carries_ids, check_codec
from gscompress.ops.budget import Budget
from gscompress.selection import check_strategy

SOLVED = ("codec", "sums", "fold")
"""The settings of `ShareOptions` that `gsc share --solve` chooses (those of the candidate that
draws best), unless they are fixed (`gscompress.pipeline.share.solve`)."""


@dataclass(frozen=True)
class ShareOptions:
    """How a share ranks, cuts and encodes a map (the options of `gsc share` of these names).

    Attributes:
        strategy: what to rank Gaussians by (`gscompress.selection.STRATEGIES`).
        codec: how the map is stored (`gscompress.io.codec.CODECS`): compact (the default,
            a fraction of fp32's bytes: docs/codecs.md, "Measurements"), fp16 or fp32 (a
            foxglove.PointCloud Foxglove draws).
        sums: send the PWAS sums (a receiver that keeps accumulating needs them); without them
            a compact share sends the score alone (fp32 and fp16 always send the sums).
        ids: send each Gaussian's id (`SHARE_IDS`: not unless asked); without them a compact
            share is smaller (docs/codecs.md, "The compact message") and the receiver numbers
            them 0..N-1 (fp32 and fp16 always send them: `sends_ids`).
        seed: seed of the random strategy.
        fold: fold what the share leaves out into the Gaussians it sends
            (`gscompress.ops.fold.cut_map`).
        spread: send the best of distinct places first (`selection.spread_ranks`): the
            strategy's order, spread over space.
    """

    strategy: str = "pwas"
    codec: str = DEFAULT_SHARE_CODEC
    sums: bool = True
    ids: bool = SHARE_IDS
    seed: int = 0
    fold: bool = True
    spread: bool = False

    def check(self) -> None:
        """Raise InputError for an unknown codec or strategy."""
        check_codec(self.codec)
        check_strategy(self.strategy)

    @property
    def sends_ids(self) -> bool:
        """Whether the share carries the ids: asked for, or always in its codec."""
        return carries_ids(self.codec, self.ids)

    def provenance(self, budget: Budget) -> dict[str, Any]:
        """The provenance step a share of `budget` (resolved) records of these options."""
        step: dict[str, Any] = {"name": "share", **budget.record(), "strategy": self.strategy}
        step.update(seed=self.seed, codec=self.codec, sums=self.sums, ids=self.sends_ids)
        step["fold"] = self.fold
        if self.spread:
            step["spread"] = True
        return step

    def results(self, source: str, budget: Budget) -> dict[str, Any]:
        """What a share of `source` (its name) under `budget` (resolved) opens its results
        with: its settings, before its counts."""
        return {
            "source": source,
            "strategy": self.strategy,
            **budget.record(),
            "codec": self.codec,
            "sums": self.sums,
            "ids": self.sends_ids,
            "fold": self.fold,
            **({"spread": True} if self.spread else {}),
        }
