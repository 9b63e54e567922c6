"""`gsc experiment`: the paper's protocol on any sequence, in one command.

Runs, each a log under DIR/runs/ with a JSON record of its settings and results beside it:
- Table 3: the whole sequence without and with PWAS pruning.
- Table 4, for each seed: agent A on the odd frames, agent B on the even frames (`split`
  "odd-even", the paper's protocol; or, with "halves", A on the first part of the frames and B
  on the last, overlapping by `overlap`: see `halves`), both with pruning, and B receiving A's
  share for every strategy at the main budget, plus B with A's whole map as the upper bound. B
  receives a share as the paper's protocol does (`mode` "merge", the default): concatenated
  into B's finished map and refined on B's frames (`gsc merge`; B's poses, so its ATE, do not
  change), or (`mode` "inject") injected before B's first frame (`gsc slam --inject`), so that
  B's tracking and mapping both use it. Table 3's PWAS-pruned run is the centralised reference
  (one agent on every frame, the agents' preset).
- Rate-distortion: B with A's share at every sweep budget for every strategy (on the first
  `sweep_seeds` seeds).

Every SLAM run is scored by `evaluate_log` on its own frames at its estimated poses. With
`refine_poses` > 0, the centralised run, A, B and every run of B with a share (or refined
without one) are also scored on A's frames, B's frames and all frames at poses refined against
the fixed map (`cross_agent`), each a step of its own. A rerun
reuses every run whose record matches its settings (and those of the runs it depends on), so an
interrupted experiment continues where it stopped and a changed setting redoes only what it
touches. With `jobs` > 1 the runs go on in worker processes, each started once the logs it reads
exist; with `executor` "ray", as tasks on a Ray cluster (`execution_ray`). A run that fails is
tried once more, then reported in results.md with its error, and the runs that need it are
not run; the rest of the experiment goes on.

Outputs in DIR: results.json (a list of rows), results.csv, results.md (tables laid out like
the paper's) and plots/ (rate-distortion, importance distribution, top-down importance map).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gscompress.errors import InputError, OptionError
from gscompress.interrupts import sigterm_interrupts
from gscompress.io.files import check_only_entries, is_within
from gscompress.pipeline.experiment.execution import LocalRunner, Runner
from gscompress.pipeline.experiment.protocol import (
    ExperimentSettings,
    plan_runs,
    plan_size,
    resolve_settings,
)
from gscompress.pipeline.experiment.report import write_reports
from gscompress.pipeline.experiment.results import result_row, verdicts_of

log = logging.getLogger(__name__)


EXECUTORS = ("local", "ray")
"""What runs an experiment's runs: this machine's processes, or Ray (`execution_ray`)."""


EXPERIMENT_ENTRIES = frozenset({"runs", "plots", "results.md", "results.csv", "results.json"})
"""Everything an experiment puts in its folder (what a rerun may write over)."""


def check_executor(
    executor: str, jobs: int, address: str | None, cpus_per_run: float | None
) -> None:
    """Refuse an executor's options that do not go together (`run_experiment`'s)."""
    if executor not in EXECUTORS:
        raise OptionError(
            f"`executor` is one of {', '.join(EXECUTORS)}, got {executor!r}",
            options=("executor",),
        )
    if executor == "ray" and jobs != 1:
        raise OptionError(
            "`jobs` is for the local executor: on Ray, the cluster's CPUs and `cpus_per_run` "
            "set how many runs go at once",
            options=("jobs", "cpus_per_run"),
        )
    if executor == "local" and (address is not None or cpus_per_run is not None):
        raise OptionError(
            "`address` and `cpus_per_run` are for `executor` ray",
            options=("address", "cpus_per_run", "executor"),
        )


def check_output_folder(out: Path, seq: Path) -> None:
    """Refuse an experiment folder that is a file, holds what an experiment does not write, or
    lies inside the sequence (a rerun continues its own folder; nothing else is written over)."""
    if out.exists() and not out.is_dir():
        raise InputError(f"output folder is a file: {out}")
    if out.is_dir():
        check_only_entries(out, EXPERIMENT_ENTRIES, "an experiment's", "give a new or empty folder")
    if is_within(out, seq):
        raise InputError(f"output folder {out} is inside the sequence folder {seq}")


def run_experiment(
    seq: str | Path,
    out_dir: str | Path,
    settings: ExperimentSettings,
    progress: Callable[[str, int, int], object] | None = None,
    jobs: int = 1,
    executor: str = "local",
    address: str | None = None,
    cpus_per_run: float | None = None,
    announce: Callable[[dict[str, Any]], object] | None = None,
) -> dict[str, Any]:
    """Run (or continue) the two-agent experiment on a sequence and write its report.

    Args:
        seq: the sequence folder or recording.
        out_dir: the experiment folder (created; reruns reuse its finished runs).
        settings: what to run.
        progress: called with (step name, steps done, steps in total) as steps start and end.
        jobs: steps run at once, each in a worker process with its share of the torch threads
            (1: one after another in this process). With as many threads per step, the results
            are the same.
        executor: "local" (this machine, `jobs` at once) or "ray" (Ray tasks: `address`
            names the cluster, None starts Ray here; each task declares `cpus_per_run` CPUs
            (default 1) and as many torch threads, and a GPU where the runs render on CUDA).
        announce: called once before the first step with what the experiment will do: its
            `steps` and an estimate of its `seconds` on this machine (`estimate.estimate`, not
            counting the steps a rerun reuses).

    Returns:
        Paths of the outputs, row count, steps run, reused and failed (name: error), and the
        PWAS-vs-random verdicts.
    """
    from gscompress.datasets import open_sequence
    from gscompress.pipeline.slam_run.start import check_working_size

    settings.check()
    check_executor(executor, jobs, address, cpus_per_run)
    seq, out = Path(seq), Path(out_dir)
    check_output_folder(out, seq)
    # a bad sequence or working size, or frames too few to give agent A (the odd positions)
    # one, fail before out_dir is made
    s, base = resolve_settings(settings)
    sequence = open_sequence(
        seq, size=base.size, frames=settings.frames, recording=settings.recording
    )
    if len(sequence) < 2:
        raise InputError(
            f"`frames` {settings.frames} leaves agent A ({settings.agent_frames(2)[0]}) no frame "
            f"of {seq}; an experiment needs at least two frames",
            options=("frames",),
        )
    check_working_size(sequence.intrinsics)
    if announce is not None:
        from gscompress.pipeline.experiment.estimate import estimate

        announce(estimate(s, base, sequence, plan_size(s)))
    runner: Runner
    if executor == "ray":
        from gscompress.pipeline.experiment.execution_ray import RayRunner

        runner = RayRunner(seq, out, s, progress, plan_size(s), address, cpus_per_run or 1.0)
    else:
        runner = LocalRunner(seq, out, s, progress, plan_size(s), jobs)
    try:
        with sigterm_interrupts():
            planned = plan_runs(runner, base, len(sequence))
            rows = [result_row(**args) for args in planned]  # waits for every step
    except BaseException:
        runner.close(cancel=True)
        raise
    runner.close(cancel=False)
    verdicts = verdicts_of(rows, s)
    full = planned[0]["run"]  # Table 3's unpruned run
    full_log = None if full.error else full.path
    paths = write_reports(out, seq, s, rows, verdicts, full_log, runner.failed)
    return {
        **paths,
        "rows": len(rows),
        "steps": runner.total,
        "reused": runner.reused,
        "failed": dict(sorted(runner.failed.items())),
        "verdicts": verdicts,
    }
