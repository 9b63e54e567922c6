"""Which runs an experiment has: its settings, the split of frames between the agents and
the graph of runs (each SLAM run, share and merge, and the results row it feeds)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from gscompress.errors import InputError, OptionError
from gscompress.io.codec import SHARE_IDS
from gscompress.ops.budget import Budget
from gscompress.pipeline.merge import DEFAULT_REFINE_VIEWS
from gscompress.pipeline.refining import DEFAULT_LR_FINAL
from gscompress.pipeline.share.cut import smallest_share_bytes
from gscompress.pipeline.share.formats import REFERENCE_FORMATS
from gscompress.pipeline.share.options import ShareOptions
from gscompress.selection import STRATEGIES, is_fraction
from gscompress.slam.views import REFINE_VIEWS

if TYPE_CHECKING:
    from gscompress.slam.config import SlamConfig


REFERENCE_TABLE = "reference"
"""The `table` of the rows of B with A's whole map in another format (`format_share`)."""


ANCHORS = ("gt", "own")
"""Where each agent's world frame starts (`ExperimentSettings.anchor`)."""


SPLITS = ("odd-even", "halves")
"""How the experiment's frames are split between agents A and B (`ExperimentSettings.split`)."""

MERGE_HOWS = ("exact", "default")
"""How the experiment's merges combine the maps (`ExperimentSettings.merge_how`)."""

PROTOCOLS: dict[str, dict[str, Any]] = {
    "commands": {"fold": True, "merge_how": "default"},
    "paper": {"fold": False, "merge_how": "exact"},
}
"""What each share and merge of an experiment does, by name: "commands", as `gsc share` and
`gsc merge` do by default (what a user of the commands gets); "paper", the paper's exact
protocol (each share the top K of its strategy, nothing folded; every Gaussian of both maps
merged and refined as one)."""

FULL_STUDY: dict[str, Any] = {
    "seeds": 3,
    "strategies": ("random", "opacity", "alpha-t", "pwas", "pwas-inf"),
    "sweep_seeds": 1,
    "every": 1,
    "refine_poses": 100,
}
"""The whole study (`gsc experiment --full`): three seeds, five strategies, the sweep with its
references on the first seed, every frame evaluated and scored across agents with 100 tracking
iterations a frame. The default (`ExperimentSettings`'s) is a first look: one seed, random
against PWAS, no sweep, every 2nd frame, 20 tracking iterations a frame (the cross-agent scoring
is most of an experiment's render passes)."""


def protocol_of(fold: bool, merge_how: str) -> str:
    """The name in `PROTOCOLS` of these share and merge settings, or "custom"."""
    got = {"fold": fold, "merge_how": merge_how}
    return next((name for name, chosen in PROTOCOLS.items() if chosen == got), "custom")


AGENT_ROWS = {
    "odd-even": ("agent A (odd frames)", "agent B (even frames)"),
    "halves": ("agent A (first part)", "agent B (last part)"),
}
"""Row names of A's and B's own runs, per split."""


B_ALONE = AGENT_ROWS["odd-even"][1]
"""Row name of B's own run (no share) in the paper's split."""


B_NO_SHARE = "B refined, no share"
"""Row name of B's map refined like a merge but with nothing merged (merge mode's control)."""


TRUE_TRANSFORM_ROW = "B + pwas at the true transform"
"""Row name (before the budget) of B with the PWAS share moved by the true transform instead
of the estimated one (anchor "own")."""


@dataclass(frozen=True)
class ExperimentSettings:
    """What an experiment runs.

    Attributes:
        preset: SLAM preset of every run (None: the config file's `preset:`, else cpu).
        config_path: optional YAML config on top of the preset.
        budget: the main share budget (Table 4): a fraction ("0.2") or bytes ("2MB").
        keep: PWAS keep ratio of the pruning stages (None: the config's).
        seeds: seeds of the two-agent protocol (SLAM seed and random selection seed).
        sweep: budgets of the rate-distortion sweep.
        sweep_seeds: how many of the seeds the sweep runs on (0: no sweep; `FULL_STUDY` has
            the whole study's seeds, strategies and sweep).
        strategies: share strategies compared: those of `gscompress.selection.STRATEGIES` and
            the PWAS ablations of `RESCORED` (by default "pwas-inf", PWAS without its proximity
            weight); a name ending in `FOR_B` (e.g. "pwas-for-b") is that strategy cut for B
            (`gsc share --for`: what B's views do not draw first).
        size: working size (W, H), or None for the config's.
        every: evaluate every N-th frame.
        lpips: compute LPIPS.
        device: torch device.
        frames: the frames the experiment uses (`all` or `START:STOP:STEP`), split between the
            agents by `split`.
        split: "odd-even": agent A gets the odd positions among the frames, agent B the even
            ones (the paper's protocol; B then sees nearly everything A saw). "halves": A gets
            the first part, B the last, overlapping by `overlap` (`halves`), so that each
            sees places the other has not.
        overlap: with split "halves", the fraction of the frames both agents get, in [0, 1).
        mode: how B receives a share: "merge" (into its finished map, then refined) or
            "inject" (before its first frame).
        merge_iters: refinement iterations of a merge.
        merge_views: what a merge refines on: B's "frames" (all) or "keyframes".
        merge_lr_final: a merge's learning rates decay to this fraction over its refinement.
        merge_how: "default" (`gsc merge`'s: aligned, the surfaces both hold resolved, the
            share's Gaussians moving as B's views see them; docs/merge.md) or "exact" (every
            Gaussian of both maps, refined as one: the paper's merge).
        fold: each share folds what it leaves out into what it sends (`gsc share`'s default);
            off, the shares are the paper's top K, so that the strategies differ only in their
            choice. `PROTOCOLS` names the two usual pairs of `fold` and `merge_how`.
        spread: every strategy's order spread over space (`gsc share --spread`).
        sums: the compact shares carry the PWAS sums (`gsc share`'s default); without them each
            Gaussian carries its score alone, so a byte budget holds more Gaussians and the
            merge has no evidence for them (`gsc share --no-sums`).
        ids: the compact shares carry the Gaussians' ids (`gsc share --ids`; not by default:
            without them a byte budget holds more Gaussians: docs/codecs.md, "The compact
            message").
        anchor: "gt": both agents start at the ground-truth pose of their first frame, so their
            maps share a frame; "own": each starts at the identity at its own first frame, A's
            map is aligned to B's (`gscompress.pipeline.align.align_agents`) and B receives
            shares moved by the estimated transform, with the PWAS share at the main budget
            also merged at the true one (from the agents' ground-truth first poses) beside it.
        refine_poses: tracking iterations of the cross-agent scoring
            (`gscompress.pipeline.experiment.cross_agent`): the centralised run, A, B and every B
            with a share scored on A's frames, on B's frames and on all frames at poses refined
            against the fixed map (0: no cross-agent scoring, each run scored on its own
            frames only).
        references: formats of `REFERENCE_FORMATS` in which A's whole map is also sent to B
            on the sweep seeds (`gscompress.pipeline.share.formats.format_share`: our fp32 codec,
            SPZ, SOG), each received like a share: the field's points on the rate-distortion
            plot. SOG is left out where splat-transform is missing (`reference_formats`).
        recording: when the sequence is a recording, its topics, pairing and ground truth
            (`gscompress.datasets.RecordingOptions`; None: chosen). The SLAM runs read it so
            and record them; every later step reopens it with the run's recorded ones.
    """

    preset: str | None = None
    config_path: str | None = None
    budget: str = "0.2"
    keep: float | None = None
    seeds: int = 1
    sweep: tuple[str, ...] = ("0.05", "0.1", "0.2", "0.4")
    sweep_seeds: int = 0
    strategies: tuple[str, ...] = ("random", "pwas")
    size: tuple[int, int] | None = None
    every: int = 2
    lpips: bool = True
    device: str = "auto"
    frames: str = "all"
    split: str = "odd-even"
    overlap: float = 0.2
    mode: str = "merge"
    merge_iters: int = 200
    merge_views: str = DEFAULT_REFINE_VIEWS
    merge_lr_final: float = DEFAULT_LR_FINAL
    merge_how: str = "default"
    fold: bool = True
    spread: bool = False
    sums: bool = True
    ids: bool = SHARE_IDS
    anchor: str = "gt"
    refine_poses: int = 20
    references: tuple[str, ...] = REFERENCE_FORMATS
    recording: Any = None

    def share_options(self, strategy: str, seed: int) -> ShareOptions:
        """How each share by `strategy` with `seed` is cut: this experiment's fold, spread,
        sums and ids, in `gsc share`'s codec."""
        return ShareOptions(
            strategy=strategy,
            seed=seed,
            fold=self.fold,
            spread=self.spread,
            sums=self.sums,
            ids=self.ids,
        )

    def agent_frames(self, n: int | None = None) -> tuple[str, str]:
        """The frame subsets of agents A and B: the odd and even positions within `frames`, or
        with split "halves" the positions `halves(n, overlap)` of the `n` frames `frames`
        selects (without `n`, only the settings are checked and ("", "") returned).
        """
        from gscompress.datasets.base import parse_frames

        usage = f"`frames` {self.frames!r}: an experiment takes all or START:STOP:STEP (from 0)"
        try:
            base = parse_frames(self.frames)
        except InputError:
            raise InputError(usage, options=("frames",)) from None
        if base.spec in ("odd", "even") or (base.start or 0) < 0 or (base.stop or 0) < 0:
            raise InputError(usage, options=("frames",))
        start, step = base.start or 0, base.step
        if self.split == "halves":
            if n is None:
                return "", ""
            a, b = halves(n, self.overlap)
            return tuple(  # type: ignore[return-value]
                f"{start + r.start * step}:{start + r.stop * step}:{step}" for r in (a, b)
            )
        if base.spec == "all":
            return "odd", "even"
        stop = "" if base.stop is None else base.stop
        return f"{start + step}:{stop}:{2 * step}", f"{start}:{stop}:{2 * step}"

    def check(self) -> None:
        """Refuse settings that cannot run (an OptionError: each comes from an option)."""
        try:
            self._check()
        except InputError as exc:
            raise OptionError(str(exc), options=exc.options) from None

    def _check(self) -> None:
        self.agent_frames()
        if self.split not in SPLITS:
            raise InputError(f"`split` is one of {', '.join(SPLITS)}", options=("split",))
        if not 0.0 <= self.overlap < 1.0:  # (nan too)
            raise InputError(
                f"`overlap` must be in [0, 1), got {self.overlap}", options=("overlap",)
            )
        if self.mode not in ("merge", "inject") or self.merge_iters < 0:
            raise InputError(
                "`mode` is merge or inject, and `merge_iters` must be >= 0",
                options=("mode", "merge_iters"),
            )
        if self.anchor not in ANCHORS:
            raise InputError(f"`anchor` is one of {', '.join(ANCHORS)}", options=("anchor",))
        if self.refine_poses < 0:
            raise InputError(
                f"`refine_poses` must be 0 or more iterations, got {self.refine_poses}",
                options=("refine_poses",),
            )
        if self.merge_how not in MERGE_HOWS:  # (the option `merge` sets it)
            raise InputError(f"`merge` is one of {', '.join(MERGE_HOWS)}", options=("merge",))
        if self.merge_views not in REFINE_VIEWS:
            raise InputError(
                f"`merge_views` is one of {', '.join(REFINE_VIEWS)}", options=("merge_views",)
            )
        if not is_fraction(self.merge_lr_final):
            raise InputError("a merge's final learning-rate fraction must be in (0, 1]")
        smallest = smallest_share_bytes()
        for text in (self.budget, *self.sweep):  # (refused now, not after the SLAM runs)
            budget = Budget.parse(text)
            if budget.budget_bytes is not None and budget.budget_bytes < smallest:
                raise InputError(
                    f"a budget of {text} cannot hold one Gaussian: a share file of one takes "
                    f"at least {smallest} B; raise the budget"
                )
        unknown_formats = sorted(set(self.references) - set(REFERENCE_FORMATS))
        if unknown_formats:
            raise InputError(
                f"unknown reference formats {unknown_formats}; choose from "
                f"{', '.join(REFERENCE_FORMATS)} (or none)"
            )
        if self.seeds < 1 or self.sweep_seeds < 0:
            raise OptionError(
                "`seeds` must be >= 1 and `sweep_seeds` >= 0", options=("seeds", "sweep_seeds")
            )
        if self.sweep_seeds > self.seeds:
            raise OptionError(
                f"`sweep_seeds` {self.sweep_seeds} is more than `seeds` {self.seeds}: the sweep "
                "runs on the first seeds",
                options=("sweep_seeds", "seeds"),
            )
        known = (*STRATEGIES, *RESCORED)
        unknown = sorted({x.removesuffix(FOR_B) for x in self.strategies} - set(known))
        if unknown or not self.strategies:
            raise InputError(
                f"unknown strategies {unknown}; choose from {', '.join(known)}, each also "
                f"as NAME{FOR_B} (cut for B: what B has not seen first)"
            )
        if self.anchor == "own" and any(x.endswith(FOR_B) for x in self.strategies):
            raise OptionError(
                f"a share cut for B ({FOR_B}) needs B's poses in A's frame: use `anchor` gt",
                options=("anchor",),
            )
        if "random" not in self.strategies or "pwas" not in self.strategies:
            raise InputError("the strategies must include random and pwas (they are compared)")


FOR_B = "-for-b"
"""Suffix of a strategy whose shares are cut for B (`gscompress.pipeline.share.receiver`)."""


RESCORED: dict[str, float | None] = {"pwas-inf": math.inf, "pwas-final": None}
"""The PWAS ablations: strategies that rank by PWAS scored again on A's finished map from A's
own frames at A's own poses (`gsc score A.mcap --sigma-d ...`), with this sigma_d. "pwas-inf"
turns the proximity weight off; "pwas-final" keeps the scene's sigma_d (None: `auto`, as the
run's), so that it separates what scoring the finished map changes from what the weight does.
A's online sums hold the weighted sums only, so PWAS without the weight must be scored again.
Their shares carry the sums scored again (the merge weighs A's evidence by them)."""


def ranked_by(strategy: str) -> str:
    """What a share of the experiment's `strategy` is cut by: a `RESCORED` ablation by PWAS (of
    its own scored log), any other by itself."""
    base = strategy.removesuffix(FOR_B)
    return "pwas" + strategy.removeprefix(base) if base in RESCORED else strategy


def halves(n: int, overlap: float) -> tuple[range, range]:
    """Positions of agents A and B among `n` frames with split "halves".

    A gets the first a = ceil(n (1 + overlap) / 2) positions, [0, a); B the last a, [n - a, n).
    Both get the 2a - n positions in the middle: `overlap` x n, or up to two more where
    rounding a up asks for it (with overlap 0 and n odd, the middle frame). For n = 50 and overlap
    0.2: A = [0, 30), B = [20, 50), 10 frames shared.
    """
    a = min(n, math.ceil(round(n * (1.0 + overlap) / 2.0, 9)))  # (round: 50 * 1.2 / 2 > 30)
    return range(0, a), range(n - a, n)


def reference_formats(s: ExperimentSettings) -> tuple[str, ...]:
    """The formats of `s.references` this machine can write: SOG only where splat-transform
    is found (`gscompress.io.sog.splat_transform`)."""
    from gscompress.io.sog import splat_transform

    return tuple(f for f in s.references if f != "sog" or splat_transform() is not None)


def plan_size(settings: ExperimentSettings) -> int:
    """How many steps an experiment has (for progress)."""
    s = settings
    main = 2 + len(s.strategies) + 1  # A, B, B+share per strategy, B+full
    main += s.mode == "merge"  # B refined without a share (the control)
    main += 2 * (s.anchor == "own")  # the alignment, B with the share at the true transform
    shares = len(s.strategies) + 1 + len(_rescored(s))  # (and each ablation's scored log)
    extra_budgets = [b for b in s.sweep if not same_budget(b, s.budget)]
    sweep = s.sweep_seeds * (len(extra_budgets) * len(s.strategies) + len(reference_formats(s)))
    sweep *= 2  # (a share and a run of B with it)
    table3 = 2
    if s.refine_poses:  # a scoring step for every run of B, A's run and the centralised run
        main += main - (s.anchor == "own")  # (every step of `main` but the alignment)
        sweep += sweep // 2  # (one per B run of the sweep, none per share)
        table3 += 1
    return table3 + s.seeds * (main + shares) + sweep


def _rescored(s: ExperimentSettings) -> list[str]:
    """The `RESCORED` ablations among the strategies, each once."""
    return [x for x in dict.fromkeys(y.removesuffix(FOR_B) for y in s.strategies) if x in RESCORED]


def resolve_settings(settings: ExperimentSettings) -> tuple[ExperimentSettings, SlamConfig]:
    """The SLAM config every run starts from (preset, then the config file, then --size and
    --keep), and the settings with the preset and keep ratio it resolved to (for the reports).

    Raises:
        OptionError: the config starts each agent at its own first frame while --anchor gt
            places both in the ground truth's (the agents' maps would not share the frame the
            experiment merges them in).
    """
    from gscompress.slam.config import resolve_config

    base = resolve_config(
        settings.preset, settings.config_path, size=settings.size, keep=settings.keep
    )
    if settings.anchor == "gt" and not base.init_from_ground_truth:
        raise OptionError(
            "the config starts each agent at its own first frame (init_from_ground_truth: "
            "false), but `anchor` gt merges them in the ground truth's frame: use `anchor` own",
            options=("anchor",),
        )
    return replace(settings, preset=base.preset, keep=base.prune.keep), base


class RunHandle(Protocol):
    """A run started by an executor: its log, its settings key and (waited for) its result,
    or why it failed."""

    path: Path
    key: str

    @property
    def result(self) -> dict[str, Any]: ...

    @property
    def error(self) -> str | None: ...


class Executor(Protocol):
    """What runs the graph of `plan_runs`: each method starts one run and returns its handle at
    once; a run waits for the handles it is given (the logs it reads) before it starts."""

    settings: ExperimentSettings

    def slam(
        self, name: str, config: Any, frames: str, inject: RunHandle | None = None
    ) -> RunHandle: ...

    def receive(
        self,
        name: str,
        receiver: RunHandle,
        share: RunHandle | None,
        config: Any,
        frames: str,
        seed: int,
        align: RunHandle | None = None,
        true: bool = False,
    ) -> RunHandle: ...

    def align(self, name: str, source: RunHandle, target: RunHandle) -> RunHandle: ...

    def share(
        self,
        name: str,
        source: RunHandle,
        budget: str,
        strategy: str,
        seed: int,
        receiver: RunHandle | None = None,
    ) -> RunHandle: ...

    def reference(self, name: str, source: RunHandle, fmt: str) -> RunHandle: ...

    def rescore(self, name: str, source: RunHandle, sigma_d: float | None) -> RunHandle: ...

    def score(
        self,
        run: RunHandle,
        own: str,
        frames: dict[str, str],
        other: RunHandle | None = None,
        align: RunHandle | None = None,
    ) -> RunHandle: ...


def plan_runs(runner: Executor, base: Any, n: int) -> list[dict[str, Any]]:
    """Start every step of the experiment (on `n` frames); the keyword arguments of `result_row`
    for each results row. Table 3's PWAS-pruned run of every frame is the centralised reference:
    one agent, the agents' preset, all the frames the two share out. With `refine_poses`, the
    centralised run, A, B and every run of B with a share (or refined without one) are also
    scored on A's frames, B's frames and all frames at refined poses (`Executor.score`)."""
    plan = _Plan(runner, n)
    rows = plan.table3(base)
    for seed in range(runner.settings.seeds):
        rows += plan.seed(base, seed)
    return rows


class _Plan:
    """The steps of one experiment, started in the order the rows list them."""

    def __init__(self, runner: Executor, n: int) -> None:
        self.runner = runner
        self.s = s = runner.settings
        frames_a, frames_b = s.agent_frames(n)
        self.frames = {"a": frames_a, "b": frames_b, "all": s.frames}
        self.own = s.anchor == "own"
        self.budgets = [s.budget] + [b for b in s.sweep if not same_budget(b, s.budget)]

    def score(
        self,
        run: RunHandle,
        own: str,
        other: RunHandle | None = None,
        align: RunHandle | None = None,
    ) -> dict[str, Any]:
        """The row's cross-scoring step (with `refine_poses`), else nothing."""
        if not self.s.refine_poses:
            return {}
        return {"cross": self.runner.score(run, own, self.frames, other, align)}

    def table3(self, base: Any) -> list[dict[str, Any]]:
        """The whole sequence without and with PWAS pruning (the centralised reference)."""
        runner, s = self.runner, self.s
        full = runner.slam("full_no_prune", base.with_overrides(**{"prune.stages": ()}), s.frames)
        pruned = runner.slam("full_pwas", base, s.frames)
        return [
            {"name": "full, no pruning", "table": "table3", "run": full},
            {"name": "full, PWAS pruning", "table": "table3", "run": pruned}
            | self.score(pruned, "all"),
        ]

    def seed(self, base: Any, seed: int) -> list[dict[str, Any]]:
        """Table 4's rows of one seed: the two agents, B alone, B with each share, with A's
        whole map and with the reference formats."""
        runner, s = self.runner, self.s
        config = base.with_overrides(seed=seed)
        if self.own:  # each agent at the identity at its own first frame
            config = config.with_overrides(init_from_ground_truth=False)
        a = runner.slam(f"s{seed}_agent_a", config, self.frames["a"])
        b = runner.slam(f"s{seed}_agent_b", config, self.frames["b"])
        agents = _Agents(
            a, b, config, seed, runner.align(f"s{seed}_align", a, b) if self.own else None
        )
        a_alone, b_alone = AGENT_ROWS[s.split]
        row = {"table": "table4", "seed": seed}
        rows = [
            {"name": a_alone, "run": a, **row} | self.score(a, "a", b, agents.align),
            {"name": b_alone, "run": b, **row} | self.score(b, "b", a, agents.align),
        ]
        if s.mode == "merge":
            alone = runner.receive(
                f"s{seed}_no_share_agent_b", b, None, config, self.frames["b"], seed
            )
            rows.append(
                {"name": B_NO_SHARE, "run": alone, **row, "strategy": "none"}
                | self.score(alone, "b", a, agents.align)
            )
        rows += self.shares(agents)
        whole = runner.share(f"s{seed}_full_share", a, "1", "pwas", seed)
        rows.append(self.received(agents, f"s{seed}_full", whole, "B + A's full map", "full"))
        for fmt in reference_formats(s) if seed < s.sweep_seeds else ():
            sent = runner.reference(f"s{seed}_whole_{fmt}_share", a, fmt)
            name = f"B + A's whole map as {fmt}"
            rows.append(
                self.received(agents, f"s{seed}_whole_{fmt}", sent, name, fmt, REFERENCE_TABLE)
            )
        return rows

    def shares(self, agents: _Agents) -> list[dict[str, Any]]:
        """B with each strategy's share at each budget (the sweep's in its seeds only)."""
        runner, s, seed = self.runner, self.s, agents.seed
        a, b = agents.a, agents.b
        scored = {x: runner.rescore(f"s{seed}_agent_a_{x}", a, RESCORED[x]) for x in _rescored(s)}
        rows = []
        for budget in self.budgets if seed < s.sweep_seeds else self.budgets[:1]:
            table = "table4" if budget == s.budget else "sweep"
            for strategy in s.strategies:
                tag = f"s{seed}_{strategy}_{_slug(budget)}"
                source = scored.get(strategy.removesuffix(FOR_B), a)
                for_b = b if strategy.endswith(FOR_B) else None
                share = runner.share(
                    f"{tag}_share", source, budget, ranked_by(strategy), seed, for_b
                )
                name = f"B + {strategy} {budget}"
                rows.append(self.received(agents, tag, share, name, strategy, table, budget))
                if self.own and table == "table4" and strategy == "pwas":
                    got = runner.receive(
                        f"{tag}_true_agent_b",
                        b,
                        share,
                        agents.config,
                        self.frames["b"],
                        seed,
                        agents.align,
                        true=True,
                    )
                    rows.append(
                        {
                            "name": f"{TRUE_TRANSFORM_ROW} {budget}",
                            "table": table,
                            "run": got,
                            "seed": seed,
                            "budget": budget,
                            "share": share,
                        }
                        | self.score(got, "b", a, agents.align)
                    )
        return rows

    def received(
        self,
        agents: _Agents,
        tag: str,
        share: RunHandle,
        name: str,
        strategy: str,
        table: str = "table4",
        budget: str = "1",
    ) -> dict[str, Any]:
        """The row of B receiving `share` (step `{tag}_agent_b`)."""
        b, align = agents.b, agents.align
        got = self.runner.receive(
            f"{tag}_agent_b", b, share, agents.config, self.frames["b"], agents.seed, align
        )
        return {
            "name": name,
            "table": table,
            "run": got,
            "seed": agents.seed,
            "strategy": strategy,
            "budget": budget,
            "share": share,
            "align": align,
        } | self.score(got, "b", agents.a, align)


@dataclass(frozen=True)
class _Agents:
    """One seed's two agents, their configuration and (with `--anchor own`) their alignment."""

    a: RunHandle
    b: RunHandle
    config: Any
    seed: int
    align: RunHandle | None


def _slug(budget: str) -> str:
    return budget.replace(".", "p").replace("%", "pct").replace(" ", "")


def same_budget(a: str, b: str) -> bool:
    """Whether two written budgets mean the same (`0.2` and `20%` do, `2%bytes` and `5%bytes`
    do not)."""
    if not a or not b:
        return False
    x, y = Budget.parse(a), Budget.parse(b)
    return (x.ratio, x.budget_bytes, x.fp32_fraction) == (y.ratio, y.budget_bytes, y.fp32_fraction)
