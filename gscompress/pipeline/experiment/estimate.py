"""How long an experiment will take, said before it starts.

Its plan's work is counted from the settings in three kinds: tracking-like iterations (a render
forward and backward with gradients to a pose only: each SLAM run's tracking, each cross-agent
scoring's pose refinement), mapping-like iterations (a render forward and backward with
gradients to every Gaussian, the mapping loss and the optimiser's step: each SLAM run's mapping
and final refinement, each merge's refinement) and evaluation renders (forward only). Each kind
is priced by timing it now, on the sequence's first two frames: the first mapped and the second
tracked and mapped with the SLAM settings' iterations cut to `CALIBRATION`; an evaluation render
is priced as a tracking iteration.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gscompress.pipeline.experiment.protocol import (
    ExperimentSettings,
    _rescored,
    halves,
    reference_formats,
    same_budget,
)

CALIBRATION = {"mapping.first_frame_iters": 10, "tracking.iters": 5, "mapping.iters": 5}
"""The iterations of the timed run: the first frame's mapping, then the second frame's tracking
and mapping."""


@dataclass(frozen=True)
class Work:
    """An amount of work of each kind (or the seconds of one unit of each)."""

    tracking: float = 0.0
    mapping: float = 0.0
    renders: float = 0.0

    def __add__(self, other: Work) -> Work:
        return Work(*(a + b for a, b in zip(self.parts(), other.parts(), strict=True)))

    def parts(self) -> tuple[float, float, float]:
        return self.tracking, self.mapping, self.renders

    def times(self, k: float) -> Work:
        """The work `k` times over."""
        return Work(*(a * k for a in self.parts()))

    def seconds(self, price: Work) -> float:
        """The work's seconds at `price` seconds a unit of each kind."""
        return sum(a * b for a, b in zip(self.parts(), price.parts(), strict=True))


def agent_frame_counts(s: ExperimentSettings, n: int) -> tuple[int, int]:
    """About how many of the `n` frames agents A and B map."""
    if s.split == "halves":
        a, b = halves(n, s.overlap)
        return len(a), len(b)
    return n // 2, n - n // 2


def plan_work(s: ExperimentSettings, base: Any, n: int) -> Work:
    """The work of the experiment's steps on `n` frames with SLAM config `base`: each SLAM run's
    tracking, mapping and final refinement iterations and its evaluation, each merge's
    refinement and evaluation, each cross-agent scoring's pose refinement and evaluation."""
    from gscompress.slam.config import final_iterations

    n_a, n_b = agent_frame_counts(s, n)

    def scored(frames: int) -> int:  # (every `every`-th frame)
        return -(-frames // s.every)

    def slam(frames: int) -> Work:
        mapping = frames * base.mapping.iters + final_iterations(base.mapping, frames)
        return Work(frames * base.tracking.iters, mapping, frames + scored(frames))

    merge = Work(0, s.merge_iters, scored(n_b)) if s.mode == "merge" else slam(n_b)
    frames = scored(n_a) + scored(n_b) + scored(n)
    scoring = Work(s.refine_poses * frames, 0, frames) if s.refine_poses > 0 else Work()
    extra_budgets = [b for b in s.sweep if not same_budget(b, s.budget)]
    received = len(s.strategies) + 1  # each strategy at the main budget, A's whole map
    received += s.mode == "merge"  # B refined without a share
    sweep = len(extra_budgets) * len(s.strategies) + len(reference_formats(s))
    per_seed = slam(n_a) + slam(n_b) + Work(0, 0, len(_rescored(s)) * n_a)
    per_seed += (merge + scoring).times(received) + scoring.times(2)  # (A and B scored too)
    total = slam(n).times(2) + scoring + per_seed.times(s.seeds)
    return total + (merge + scoring).times(s.sweep_seeds * sweep)


def render_passes(s: ExperimentSettings, base: Any, n: int) -> int:
    """Every render forward (and backward, where it has one) of the plan (`plan_work`)."""
    return round(sum(plan_work(s, base, n).parts()))


def unit_seconds(sequence: Any, base: Any, device: str = "auto") -> Work:
    """Seconds of one tracking iteration, one mapping iteration and one evaluation render at the
    working size, timed now: the run of `base` (its pruning stages and final refinement off)
    over the sequence's first two frames with the iterations of `CALIBRATION`. The kernels are
    loaded before the clock starts."""
    from gscompress.render import resolve_backend, resolve_device
    from gscompress.slam.system import SlamSystem

    config = base.with_overrides(**CALIBRATION, **{"prune.stages": (), "mapping.final_iters": 0})
    torch_device = resolve_device(device, base.backend)
    resolve_backend(base.backend, torch_device)
    system = SlamSystem(config, sequence.intrinsics, torch_device, total_frames=None)
    first = system.process(sequence.frame(0)).ms
    mapping = first["mapping"] / CALIBRATION["mapping.first_frame_iters"]
    tracking = mapping  # (a sequence of one frame: no tracking to time)
    if len(sequence) > 1:
        second = system.process(sequence.frame(1)).ms
        tracking = second["tracking"] / CALIBRATION["tracking.iters"]
        mapping = second["mapping"] / CALIBRATION["mapping.iters"]
    return Work(tracking / 1000, mapping / 1000, tracking / 1000)


def estimate(s: ExperimentSettings, base: Any, sequence: Any, steps: int) -> dict[str, Any]:
    """What `gsc experiment` says before it starts: its steps, render passes and seconds."""
    work = plan_work(s, base, len(sequence))
    price = unit_seconds(sequence, base, s.device)
    return {
        "steps": steps,
        "render_passes": round(sum(work.parts())),
        "seconds": work.seconds(price),
    }
