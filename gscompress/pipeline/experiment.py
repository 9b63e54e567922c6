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

Every SLAM run is scored by `evaluate_log` on its own frames at its estimated poses. A rerun
reuses every run whose record matches its settings (and those of the runs it depends on), so an
interrupted experiment continues where it stopped and a changed setting redoes only what it
touches. With `jobs` > 1 the runs go on in worker processes, each started once the logs it reads
exist.

Outputs in DIR: results.json (a list of rows), results.csv, results.md (tables laid out like
the paper's) and plots/ (rate-distortion, importance distribution, top-down importance map).
"""

from __future__ import annotations

import contextlib
import csv
import functools
import hashlib
import json
import logging
import math
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import (
    CancelledError,
    Future,
    ProcessPoolExecutor,
    ThreadPoolExecutor,
    wait,
)
from dataclasses import dataclass, replace
from multiprocessing.queues import SimpleQueue
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gscompress import __version__
from gscompress.errors import GscError, InputError, OptionError
from gscompress.interrupts import sigterm_interrupts
from gscompress.io.files import (
    abandoned_files,
    check_only_entries,
    is_within,
    json_text,
    read_json,
    write_text_atomic,
)
from gscompress.io.mcap_log import LogReader
from gscompress.ops.budget import Budget
from gscompress.pipeline.merge import DEFAULT_REFINE_VIEWS
from gscompress.pipeline.offline import log_edges, smallest_share_bytes
from gscompress.pipeline.refine import DEFAULT_LR_FINAL
from gscompress.selection import STRATEGIES, is_fraction, strategy_scores
from gscompress.slam.config import REFINE_VIEWS

if TYPE_CHECKING:
    from gscompress.slam.config import SlamConfig

log = logging.getLogger(__name__)

SPLITS = ("odd-even", "halves")
"""How the experiment's frames are split between agents A and B (`ExperimentSettings.split`)."""

AGENT_ROWS = {
    "odd-even": ("agent A (odd frames)", "agent B (even frames)"),
    "halves": ("agent A (first part)", "agent B (last part)"),
}
"""Row names of A's and B's own runs, per split."""

B_ALONE = AGENT_ROWS["odd-even"][1]
"""Row name of B's own run (no share) in the paper's split."""
B_NO_SHARE = "B refined, no share"
"""Row name of B's map refined like a merge but with nothing merged (merge mode's control)."""

ROW_KEYS = (
    "name", "table", "seed", "strategy", "budget", "frames", "ate_rmse_cm", "ate_splatam_cm",
    "ate_reason", "psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm", "gaussians", "bytes",
    "share_gaussians", "share_bytes", "seconds_per_frame", "log",
)  # fmt: skip
"""Columns of results.csv (every row of results.json has them)."""


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
        sweep_seeds: how many of the seeds the sweep runs on.
        strategies: share strategies compared.
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
    """

    preset: str | None = None
    config_path: str | None = None
    budget: str = "0.2"
    keep: float | None = None
    seeds: int = 3
    sweep: tuple[str, ...] = ("0.05", "0.1", "0.2", "0.4")
    sweep_seeds: int = 1
    strategies: tuple[str, ...] = ("random", "opacity", "alpha-t", "pwas")
    size: tuple[int, int] | None = None
    every: int = 1
    lpips: bool = True
    device: str = "auto"
    frames: str = "all"
    split: str = "odd-even"
    overlap: float = 0.2
    mode: str = "merge"
    merge_iters: int = 200
    merge_views: str = DEFAULT_REFINE_VIEWS
    merge_lr_final: float = DEFAULT_LR_FINAL

    def agent_frames(self, n: int | None = None) -> tuple[str, str]:
        """The frame subsets of agents A and B: the odd and even positions within `frames`, or
        with split "halves" the positions `halves(n, overlap)` of the `n` frames `frames`
        selects (without `n`, only the settings are checked and ("", "") returned).
        """
        from gscompress.datasets.base import parse_frames

        usage = f"--frames {self.frames!r}: an experiment takes all or START:STOP:STEP (from 0)"
        try:
            base = parse_frames(self.frames)
        except InputError:
            raise InputError(usage) from None
        if base.spec in ("odd", "even") or (base.start or 0) < 0 or (base.stop or 0) < 0:
            raise InputError(usage)
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
            raise OptionError(str(exc)) from None

    def _check(self) -> None:
        self.agent_frames()
        if self.split not in SPLITS:
            raise InputError(f"--split is one of {', '.join(SPLITS)}")
        if not 0.0 <= self.overlap < 1.0:  # (nan too)
            raise InputError(f"--overlap must be in [0, 1), got {self.overlap}")
        if self.mode not in ("merge", "inject") or self.merge_iters < 0:
            raise InputError("--mode is merge or inject, and --merge-iters must be >= 0")
        if self.merge_views not in REFINE_VIEWS:
            raise InputError(f"--merge-views is one of {', '.join(REFINE_VIEWS)}")
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
        if self.seeds < 1 or self.sweep_seeds < 0:
            raise OptionError("--seeds must be >= 1 and --sweep-seeds >= 0")
        if self.sweep_seeds > self.seeds:
            raise OptionError(
                f"--sweep-seeds {self.sweep_seeds} is more than --seeds {self.seeds}: the sweep "
                "runs on the first seeds"
            )
        unknown = sorted(set(self.strategies) - set(STRATEGIES))
        if unknown or not self.strategies:
            raise InputError(f"unknown strategies {unknown}; choose from {', '.join(STRATEGIES)}")
        if "random" not in self.strategies or "pwas" not in self.strategies:
            raise InputError("the strategies must include random and pwas (they are compared)")


def halves(n: int, overlap: float) -> tuple[range, range]:
    """Positions of agents A and B among `n` frames with split "halves".

    A gets the first a = ceil(n (1 + overlap) / 2) positions, [0, a); B the last a, [n - a, n).
    Both get the 2a - n positions in the middle: `overlap` x n, or up to two more where
    rounding a up asks for it (with overlap 0 and n odd, the middle frame). For n = 50 and overlap
    0.2: A = [0, 30), B = [20, 50), 10 frames shared.
    """
    a = min(n, math.ceil(round(n * (1.0 + overlap) / 2.0, 9)))  # (round: 50 * 1.2 / 2 > 30)
    return range(0, a), range(n - a, n)


@dataclass
class _Record:
    """One step: its log, its settings key and what it reported (waited for when running in a
    worker process)."""

    path: Path
    key: str
    _result: dict[str, Any] | None = None
    _future: Future[dict[str, Any]] | None = None

    @property
    def result(self) -> dict[str, Any]:
        if self._result is None:
            assert self._future is not None
            self._result = self._future.result()
        return self._result


def _score(log_path: Path, seq: Path, every: int, lpips: bool, device: str) -> dict[str, Any]:
    """`gsc eval` of a run on its own frames (without the per-frame list)."""
    from gscompress.pipeline.evaluate import evaluate_log

    scores = evaluate_log(log_path, seq, every=every, lpips=lpips, device=device)
    scores.pop("per_frame", None)
    return scores


# The steps' work, as module functions of plain arguments so that worker processes can run them.


def _slam_job(
    path: Path, seq: Path, config: Any, frames: str, inject: Path | None, s: ExperimentSettings
) -> dict[str, Any]:
    from gscompress.pipeline.slam_run import slam_file

    run = slam_file(seq, path, config=config, frames=frames, device=s.device, inject=inject,
                    force=True)  # fmt: skip
    return {"slam": run, "eval": _score(path, seq, s.every, s.lpips, s.device)}


def _merge_job(
    path: Path, seq: Path, receiver: Path, share: Path | None, frames: str, seed: int,
    s: ExperimentSettings,
) -> dict[str, Any]:  # fmt: skip
    from gscompress.pipeline.merge import merge_logs

    merged = merge_logs(receiver, share, path, seq=seq, frames=frames, iters=s.merge_iters,
                        views=s.merge_views, lr_final=s.merge_lr_final, device=s.device,
                        seed=seed, force=True)  # fmt: skip
    return {"merge": merged, "eval": _score(path, seq, s.every, s.lpips, s.device)}


def _share_job(path: Path, source: Path, budget: str, strategy: str, seed: int) -> dict[str, Any]:
    from gscompress.pipeline.offline import share_log

    return share_log(source, path, budget, strategy=strategy, seed=seed, force=True)


def _digest(result: dict[str, Any]) -> str:
    """What a run record checks its result against: a record damaged (or edited) since it was
    written is a run to do again, not a traceback in the tables."""
    return hashlib.sha256(json_text(result).encode()).hexdigest()


def _intact(record: dict[str, Any]) -> bool:
    """Whether a run record's result is as written (records before the digest: a mapping)."""
    result, digest = record.get("result"), record.get("result_sha256")
    return isinstance(result, dict) and (digest is None or digest == _digest(result))


def _init_worker(threads: int, pids: SimpleQueue[int]) -> None:
    """A worker process: its share of the threads; Ctrl-C is for the run it is in (which
    stops after its frame, as `gsc slam` does), not for a worker waiting for work. Its pid goes
    to `pids`, so that the runner can signal exactly its own workers. It ends with the runner:
    a runner killed outright (SIGKILL) cannot stop its workers, which would otherwise wait for
    work forever. Only its warnings reach the console (lines of another process cannot be
    written above the runner's progress bar, so `gsc -v` speaks for --jobs 1 alone)."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    pids.put(os.getpid())
    torch.set_num_threads(threads)
    threading.Thread(target=_end_with_parent, name="end-with-parent", daemon=True).start()


def _end_with_parent() -> None:
    """Wait for this process's parent to end, then end at once. A runner that ends normally
    has joined its workers before, so this only acts when it was killed; the run under way
    is cut, as the runner's own was (it keeps no record, so a rerun redoes it)."""
    parent = multiprocessing.parent_process()
    if parent is not None:
        parent.join()
        os._exit(1)


class _Runner:
    """Runs the steps of an experiment, reusing those whose records match.

    With `jobs` > 1 the steps run in that many worker processes, each as soon as the steps it
    reads have finished, with the torch threads of this process shared among them.
    """

    def __init__(
        self,
        seq: Path,
        out: Path,
        settings: ExperimentSettings,
        progress: Callable[[str, int, int], object] | None,
        total: int,
        jobs: int = 1,
    ) -> None:
        self.seq, self.settings, self.progress, self.total = seq, settings, progress, total
        self.runs = out / "runs"
        self.runs.mkdir(parents=True, exist_ok=True)
        for unfinished in abandoned_files(self.runs):  # a killed runner's workers' (no record
            unfinished.unlink(missing_ok=True)  # points at them: their steps are redone)
        self.done = 0
        self.reused = 0
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._pool: ProcessPoolExecutor | None = None
        self._worker_pids: SimpleQueue[int] | None = None
        self._waiters: ThreadPoolExecutor | None = None
        jobs = min(jobs, total)  # no more workers than steps
        if jobs > 1:
            import torch

            available = torch.get_num_threads()
            threads = max(1, available // jobs)
            if threads * jobs != available:
                log.warning(
                    "%d torch threads do not split evenly over %d jobs: each run gets %d (%d in "
                    "all; see gsc --threads)", available, jobs, threads, threads * jobs,
                )  # fmt: skip
            spawn = multiprocessing.get_context("spawn")  # fork is unsafe once OpenMP has run
            self._worker_pids = spawn.SimpleQueue()  # each worker's pid, sent as it starts
            self._pool = ProcessPoolExecutor(
                jobs, spawn, _init_worker, (threads, self._worker_pids)
            )
            # one waiting thread per step: each starts its job once the steps it reads are done
            # (they were submitted before it, so they are under way: no waiting in a circle)
            self._waiters = ThreadPoolExecutor(max(1, total))

    def close(self, cancel: bool) -> None:
        """Wait for the steps under way; with `cancel`, start no more and stop the SLAM runs
        under way after their frame (a stopped run keeps no record, so a rerun redoes it)."""
        if cancel:
            self._stopping.set()
            if self._worker_pids is not None:  # a worker between runs ignores it, a merge too
                workers = set()
                while not self._worker_pids.empty():
                    workers.add(self._worker_pids.get())
                for pid in workers:
                    with contextlib.suppress(OSError):  # ended meanwhile
                        os.kill(pid, signal.SIGINT)
        for pool in (self._waiters, self._pool):
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=cancel)

    def _key(self, spec: dict[str, Any]) -> str:  # (of what a run is; _digest: of what it gave)
        text = json.dumps({"tool": __version__, **spec}, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def _step(
        self,
        name: str,
        spec: dict[str, Any],
        job: functools.partial[dict[str, Any]],
        after: Sequence[_Record] = (),
        extra: Callable[[], dict[str, Any]] | None = None,
    ) -> _Record:
        """Run `job(log path)` unless a record with the same key exists; `after`: the steps
        whose logs it reads; `extra()`: what the record adds to the job's result."""
        path = self.runs / f"{name}.mcap"
        record_path = self.runs / f"{name}.json"
        key = self._key(spec)
        if path.is_file() and record_path.is_file():
            try:  # a damaged record is a run to do again
                saved = read_json(record_path, "run record")
            except GscError:
                saved = None
            if isinstance(saved, dict) and saved.get("key") == key and _intact(saved):
                self.reused += 1
                self._finished(name)
                return _Record(path, key, saved["result"])
        if self._pool is None or self._waiters is None:
            if self.progress is not None:
                self.progress(name, self.done, self.total)
            result = self._record(name, record_path, spec, key, job(path), extra)
            return _Record(path, key, result)

        def run() -> dict[str, Any]:
            for step in after:
                _ = step.result  # waits; a failed step fails this one
            if self._stopping.is_set():
                raise CancelledError
            assert self._pool is not None
            future = self._pool.submit(job, path)
            while not wait([future], timeout=0.2).done:
                if self._stopping.is_set() and future.cancel():  # queued, not started
                    raise CancelledError
            return self._record(name, record_path, spec, key, future.result(), extra)

        return _Record(path, key, _future=self._waiters.submit(run))

    def _record(
        self,
        name: str,
        record_path: Path,
        spec: dict[str, Any],
        key: str,
        result: dict[str, Any],
        extra: Callable[[], dict[str, Any]] | None,
    ) -> dict[str, Any]:
        result = {**result, **(extra() if extra else {})}
        record = {"key": key, "spec": spec, "result": result, "result_sha256": _digest(result)}
        write_text_atomic(record_path, json_text(record, indent=1))
        self._finished(name)
        return result

    def _finished(self, name: str) -> None:
        with self._lock:
            self.done += 1
            if self.progress is not None:
                self.progress(name, self.done, self.total)

    def slam(self, name: str, config: Any, frames: str, inject: _Record | None = None) -> _Record:
        """A SLAM run on `frames`, evaluated on them."""
        s = self.settings
        spec = {
            "kind": "slam", "sequence": str(self.seq.resolve()), "config": config.to_dict(),
            "frames": frames, "inject": inject.key if inject else None, "every": s.every,
            "lpips": s.lpips,
        }  # fmt: skip
        job = functools.partial(
            _slam_job, seq=self.seq, config=config, frames=frames,
            inject=inject.path if inject else None, s=s,
        )  # fmt: skip
        return self._step(name, spec, job, after=[inject] if inject else [])

    def receive(
        self,
        name: str,
        receiver: _Record,
        share: _Record | None,
        config: Any,
        frames: str,
        seed: int,
    ) -> _Record:
        """Agent B with a share: merged into B's map and refined, or injected into a new run.

        With `share` None (merge mode only): B's map refined the same way without a share, the
        control that separates what the share brings from what the refinement brings.
        """
        s = self.settings
        if s.mode == "inject":  # its own name: both modes' runs can share one folder
            assert share is not None
            return self.slam(f"{name}_inject", config, frames, inject=share)
        spec = {
            "kind": "merge", "receiver": receiver.key, "share": share.key if share else None,
            "frames": frames, "iters": s.merge_iters, "views": s.merge_views,
            "lr_final": s.merge_lr_final, "seed": seed, "every": s.every, "lpips": s.lpips,
        }  # fmt: skip
        job = functools.partial(
            _merge_job, seq=self.seq, receiver=receiver.path,
            share=share.path if share else None, frames=frames, seed=seed, s=s,
        )  # fmt: skip
        after = [receiver, share] if share else [receiver]
        return self._step(name, spec, job, after, extra=lambda: {"slam": receiver.result["slam"]})

    def share(self, name: str, source: _Record, budget: str, strategy: str, seed: int) -> _Record:
        """A share of `source`'s map."""
        spec = {"kind": "share", "source": source.key, "budget": budget, "strategy": strategy,
                "seed": seed}  # fmt: skip
        job = functools.partial(
            _share_job, source=source.path, budget=budget, strategy=strategy, seed=seed
        )
        return self._step(name, spec, job, after=[source])


EXPERIMENT_ENTRIES = frozenset({"runs", "plots", "results.md", "results.csv", "results.json"})
"""Everything an experiment puts in its folder (what a rerun may write over)."""


def plan_size(settings: ExperimentSettings) -> int:
    """How many steps an experiment has (for progress)."""
    s = settings
    main = 2 + len(s.strategies) + 1  # A, B, B+share per strategy, B+full
    main += s.mode == "merge"  # B refined without a share (the control)
    shares = len(s.strategies) + 1
    extra_budgets = [b for b in s.sweep if not _same_budget(b, s.budget)]
    sweep = s.sweep_seeds * len(extra_budgets) * len(s.strategies) * 2
    return 2 + s.seeds * (main + shares) + sweep


def resolve_settings(settings: ExperimentSettings) -> tuple[ExperimentSettings, SlamConfig]:
    """The SLAM config every run starts from (preset, then the config file, then --size and
    --keep), and the settings with the preset and keep ratio it resolved to (for the reports)."""
    from gscompress.slam.config import resolve_config

    base = resolve_config(
        settings.preset, settings.config_path, size=settings.size, keep=settings.keep
    )
    return replace(settings, preset=base.preset, keep=base.prune.keep), base


def run_experiment(
    seq: str | Path,
    out_dir: str | Path,
    settings: ExperimentSettings,
    progress: Callable[[str, int, int], object] | None = None,
    jobs: int = 1,
) -> dict[str, Any]:
    """Run (or continue) the two-agent experiment on a sequence and write its report.

    Args:
        seq: the sequence folder.
        out_dir: the experiment folder (created; reruns reuse its finished runs).
        settings: what to run.
        progress: called with (step name, steps done, steps in total) as steps start and end.
        jobs: steps run at once, each in a worker process with its share of the torch threads
            (1: one after another in this process). With as many threads per step, the results
            are the same.

    Returns:
        Paths of the outputs, row count, steps run and reused, and the PWAS-vs-random verdicts.
    """
    from gscompress.datasets import open_sequence
    from gscompress.pipeline.slam_run import check_working_size

    settings.check()
    seq, out = Path(seq), Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"output folder is a file: {out}")
    if out.is_dir():  # a rerun continues its own folder; nothing else is written over
        check_only_entries(out, EXPERIMENT_ENTRIES, "an experiment's", "give a new or empty folder")
    if is_within(out, seq):
        raise InputError(f"output folder {out} is inside the sequence folder {seq}")
    # a bad sequence or working size, or frames too few to give agent A (the odd positions)
    # one, fail before out_dir is made
    s, base = resolve_settings(settings)
    sequence = open_sequence(seq, size=base.size, frames=settings.frames)
    if len(sequence) < 2:
        raise InputError(
            f"--frames {settings.frames} leaves agent A ({settings.agent_frames(2)[0]}) no frame "
            f"of {seq}; an experiment needs at least two frames"
        )
    check_working_size(sequence.intrinsics)
    runner = _Runner(seq, out, s, progress, plan_size(s), jobs)
    try:
        with sigterm_interrupts():
            planned = _plan(runner, base, len(sequence))
            rows = [_row(*args) for args in planned]  # waits for every step
    except BaseException:
        runner.close(cancel=True)
        raise
    runner.close(cancel=False)
    verdicts = _verdicts(rows, s)
    full = planned[0][2]  # Table 3's unpruned run
    paths = _write_reports(out, seq, s, rows, verdicts, full.path)
    return {
        **paths,
        "rows": len(rows),
        "steps": runner.total,
        "reused": runner.reused,
        "verdicts": verdicts,
    }


def _plan(runner: _Runner, base: Any, n: int) -> list[tuple[Any, ...]]:
    """Start every step of the experiment (on `n` frames); the arguments of `_row` for each
    results row. Table 3's PWAS-pruned run of every frame is the centralised reference: one
    agent, the agents' preset, all the frames the two share out."""
    s = runner.settings
    rows: list[tuple[Any, ...]] = []
    frames_a, frames_b = s.agent_frames(n)
    a_alone, b_alone = AGENT_ROWS[s.split]
    full = runner.slam("full_no_prune", base.with_overrides(**{"prune.stages": ()}), s.frames)
    pruned = runner.slam("full_pwas", base, s.frames)
    rows.append(("full, no pruning", "table3", full))
    rows.append(("full, PWAS pruning", "table3", pruned))

    budgets = [s.budget] + [b for b in s.sweep if not _same_budget(b, s.budget)]
    for seed in range(s.seeds):
        config = base.with_overrides(seed=seed)
        a = runner.slam(f"s{seed}_agent_a", config, frames_a)
        b = runner.slam(f"s{seed}_agent_b", config, frames_b)
        rows.append((a_alone, "table4", a, seed))
        rows.append((b_alone, "table4", b, seed))
        if s.mode == "merge":
            alone = runner.receive(f"s{seed}_no_share_agent_b", b, None, config, frames_b, seed)
            rows.append((B_NO_SHARE, "table4", alone, seed, "none"))
        for budget in budgets if seed < s.sweep_seeds else budgets[:1]:
            table = "table4" if budget == s.budget else "sweep"
            for strategy in s.strategies:
                tag = f"s{seed}_{strategy}_{_slug(budget)}"
                share = runner.share(f"{tag}_share", a, budget, strategy, seed)
                got = runner.receive(f"{tag}_agent_b", b, share, config, frames_b, seed)
                rows.append((f"B + {strategy} {budget}", table, got, seed, strategy, budget, share))
        whole = runner.share(f"s{seed}_full_share", a, "1", "pwas", seed)
        got = runner.receive(f"s{seed}_full_agent_b", b, whole, config, frames_b, seed)
        rows.append(("B + A's full map", "table4", got, seed, "full", "1", whole))
    return rows


def _slug(budget: str) -> str:
    return budget.replace(".", "p").replace("%", "pct").replace(" ", "")


def _row(
    name: str,
    table: str,
    run: _Record,
    seed: int | None = None,
    strategy: str = "",
    budget: str = "",
    share: _Record | None = None,
) -> dict[str, Any]:
    """A results row from a SLAM run's record (and the share it received)."""
    ev, slam = run.result["eval"], run.result["slam"]
    row = {key: ev.get(key) for key in ROW_KEYS}
    row.update(
        name=name, table=table, seed=seed, strategy=strategy, budget=budget,
        frames=ev.get("frames"), seconds_per_frame=slam.get("seconds_per_frame"),
        share_gaussians=share.result.get("selected") if share else None,
        share_bytes=share.result.get("bytes") if share else None,
        log=f"runs/{run.path.name}",
    )  # fmt: skip
    return row


def _same_budget(a: str, b: str) -> bool:
    """Whether two written budgets mean the same (`0.2` and `20%` do)."""
    if not a or not b:
        return False
    x, y = Budget.parse(a), Budget.parse(b)
    return (x.ratio, x.budget_bytes) == (y.ratio, y.budget_bytes)


def _sweep_rows(
    rows: list[dict[str, Any]], s: ExperimentSettings, budget: str, strategy: str | None = None
) -> list[dict]:
    """Rows of B with a share at `budget` on the sweep seeds (the main budget's included), of
    one strategy or (None) of every compared one."""
    return [
        r for r in rows
        if r["table"] in ("table4", "sweep")
        and (r["strategy"] == strategy if strategy else r["strategy"] in s.strategies)
        and r["seed"] is not None and r["seed"] < s.sweep_seeds
        and _same_budget(r["budget"], budget)
    ]  # fmt: skip


def rate_distortion_curves(
    rows: list[dict[str, Any]], s: ExperimentSettings
) -> dict[str, list[tuple[float, float | None, float | None]]]:
    """(share bytes, PSNR, ATE cm) of B per strategy over the sweep budgets, means over the
    sweep seeds, sorted by bytes.

    Each strategy's curve starts at B without a share (0 bytes: "B refined, no share" in merge
    mode, B's own run in inject mode), the point every share is a gain over; "full" is the one
    point of A's whole map, the upper end.
    """
    seeds = [r for r in rows if r["seed"] is not None and r["seed"] < s.sweep_seeds]
    reference = B_NO_SHARE if s.mode == "merge" else AGENT_ROWS[s.split][1]
    base = [r for r in seeds if r["name"] == reference]

    def point(group: list[dict[str, Any]]) -> tuple[float, float | None, float | None]:
        size = _mean([r["share_bytes"] or 0 for r in group]) or 0.0
        return size, _mean([r["psnr"] for r in group]), _mean([r["ate_rmse_cm"] for r in group])

    curves: dict[str, list[tuple[float, float | None, float | None]]] = {}
    for strategy in s.strategies:
        groups = [_sweep_rows(rows, s, budget, strategy) for budget in s.sweep]
        shared = [point(group) for group in groups if group]
        if shared:
            start = [point(base)] if base else []
            curves[strategy] = sorted(start + shared, key=lambda p: p[0])
    full = [r for r in seeds if r["strategy"] == "full"]
    if full and curves:
        curves["full"] = [point(full)]
    return curves


def _mean(values: Sequence[Any]) -> float | None:
    numbers = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(np.mean(numbers)) if numbers else None


def paired_difference(group: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """PWAS minus random in `key`, paired by seed, over the rows of one budget.

    Seeds without a finite value for both strategies are left out. Returns the number of pairs,
    the mean difference, its standard error (sample standard deviation / sqrt(pairs); None
    below two pairs) and how many differences are positive and negative.
    """
    values: dict[int, dict[str, float]] = {}
    for row in group:
        value = row.get(key)
        if row["strategy"] in ("pwas", "random") and value is not None and math.isfinite(value):
            values.setdefault(row["seed"], {})[row["strategy"]] = float(value)
    diffs = np.array([v["pwas"] - v["random"] for v in values.values() if len(v) == 2])
    n = len(diffs)
    return {
        "pairs": n,
        "mean": float(diffs.mean()) if n else None,
        "se": float(diffs.std(ddof=1) / math.sqrt(n)) if n > 1 else None,
        "positive": int((diffs > 0).sum()),
        "negative": int((diffs < 0).sum()),
    }


def _verdicts(rows: list[dict[str, Any]], s: ExperimentSettings) -> dict[str, Any]:
    """PWAS against random: per seed at the main budget, and per budget in the sweep."""

    def pick(table: str, strategy: str, budget: str, seed: int) -> dict[str, Any] | None:
        for row in rows:
            if (row["table"], row["strategy"], row["budget"], row["seed"]) == (
                table, strategy, budget, seed,
            ):  # fmt: skip
                return row
        return None

    psnr_wins = ate_wins = 0
    per_seed = []
    for seed in range(s.seeds):
        p, r = pick("table4", "pwas", s.budget, seed), pick("table4", "random", s.budget, seed)
        assert p is not None and r is not None
        psnr_win = (p["psnr"] or 0) > (r["psnr"] or 0)
        ate_win = (p["ate_rmse_cm"] or math.inf) < (r["ate_rmse_cm"] or math.inf)
        psnr_wins += psnr_win
        ate_wins += ate_win
        per_seed.append({"seed": seed, "pwas_beats_random_psnr": psnr_win,
                         "pwas_beats_random_ate": ate_win})  # fmt: skip
    sweep = []
    for budget in s.sweep:
        group = _sweep_rows(rows, s, budget)
        mp = _mean([r["psnr"] for r in group if r["strategy"] == "pwas"])
        mr = _mean([r["psnr"] for r in group if r["strategy"] == "random"])
        if mp is None or mr is None:
            continue
        psnr = paired_difference(group, "psnr")
        ate = paired_difference(group, "ate_rmse_cm")
        sweep.append({"budget": budget, "pwas_psnr": mp, "random_psnr": mr,
                      "pwas_at_or_above_random": mp >= mr, "pairs": psnr["pairs"],
                      "psnr_difference": psnr["mean"], "psnr_difference_se": psnr["se"],
                      "pwas_higher_psnr": psnr["positive"],
                      "ate_difference_cm": ate["mean"], "ate_difference_se_cm": ate["se"],
                      "pwas_lower_ate": ate["negative"]})  # fmt: skip
    return {
        "budget": s.budget,
        "seeds": s.seeds,
        "mode": s.mode,
        "pwas_beats_random_psnr": psnr_wins,
        "pwas_beats_random_ate": ate_wins,
        "per_seed": per_seed,
        "sweep": sweep,
    }


# ------------------------------------------------------------------------------------ reports


def _fmt(value: Any, spec: str = ".2f") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return format(value, spec)


def _mean_cell(group: list[dict[str, Any]], key: str, spec: str = ".2f") -> str:
    """The mean of `key` over a group of rows, formatted for a table (n/a without values)."""
    return _fmt(_mean([r[key] for r in group]), spec)


def _plus_minus(mean: float | None, se: float | None, spec: str) -> str:
    """`mean ± se` (`mean` alone without a standard error; n/a without a mean)."""
    if mean is None or se is None:
        return _fmt(mean, "+" + spec)
    return f"{mean:+{spec}} ± {se:{spec}}"


def _write_reports(
    out: Path,
    seq: Path,
    s: ExperimentSettings,
    rows: list[dict[str, Any]],
    verdicts: dict[str, Any],
    full_log: Path,
) -> dict[str, str]:
    """results.json, results.csv, results.md and plots/*.png."""
    write_text_atomic(out / "results.json", json_text(rows, indent=1))
    write_text_atomic(out / "results.csv", _csv(rows))
    plots = _plots(out / "plots", rows, s, full_log)
    write_text_atomic(out / "results.md", _markdown(seq, s, rows, verdicts, plots, out))
    return {
        "results_md": str(out / "results.md"),
        "results_csv": str(out / "results.csv"),
        "results_json": str(out / "results.json"),
        "plots": ", ".join(str(p) for p in plots),
    }


def _csv(rows: list[dict[str, Any]]) -> str:
    import io

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=ROW_KEYS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in ROW_KEYS})
    return buffer.getvalue()


def _receive_text(s: ExperimentSettings) -> str:
    if s.mode == "inject":
        return "B's run starts with the share injected. "
    return (
        f"B merges a share into its map and refines it ({s.merge_iters} iterations on its "
        f"{s.merge_views}, the learning rates decaying to {s.merge_lr_final:g} of their start; "
        "B's poses, so its ATE, do not change). "
    )


def _markdown(
    seq: Path,
    s: ExperimentSettings,
    rows: list[dict[str, Any]],
    verdicts: dict[str, Any],
    plots: list[Path],
    out: Path,
) -> str:
    frames_a, frames_b = (
        next((r["frames"] for r in rows if r["name"] == name), "?") for name in AGENT_ROWS[s.split]
    )
    split = (
        "B maps the even frames, A the odd ones"
        if s.split == "odd-even"
        else f"A maps the first part of the frames, B the last, overlapping by {s.overlap:g}"
    )
    lines = [
        f"# gsc experiment: {seq.name}",
        "",
        f"Frames `{s.frames}` (A: `{frames_a}`, B: `{frames_b}`); "
        + _receive_text(s)
        + f"Preset `{s.preset}`"
        + (f" + `{s.config_path}`" if s.config_path else "")
        + f", keep {s.keep}, budget {s.budget}, seeds {s.seeds}, evaluated every {s.every} "
        "frame(s) of each run's own frames at its estimated poses (PSNR/SSIM on valid-depth "
        "pixels; ATE RMSE after SE(3) alignment, cm). gscompress " + __version__ + ".",
        "",
        "## Table 3: PWAS pruning over the whole sequence",
        "",
        "| Method | Gaussians | Reduction | PSNR | SSIM | LPIPS | ATE RMSE (cm) |",
        "|---|---|---|---|---|---|---|",
    ]
    t3 = [r for r in rows if r["table"] == "table3"]
    base = t3[0]["gaussians"] or 1
    for r in t3:
        reduction = 100.0 * (1 - (r["gaussians"] or 0) / base)
        lines.append(
            f"| {r['name']} | {r['gaussians']} | {reduction:.1f}% | {_fmt(r['psnr'])} | "
            f"{_fmt(r['ssim'], '.3f')} | {_fmt(r['lpips'], '.3f')} | "
            f"{_fmt(r['ate_rmse_cm'], '.3f')} |"
        )
    lines += [
        "",
        f"## Table 4: sharing at budget {s.budget} ({split})",
        "",
        "| Seed | Method | ATE RMSE (cm) | PSNR | SSIM | LPIPS | Gaussians | Shared "
        "| Bytes shared |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    t4 = [r for r in rows if r["table"] == "table4"]
    for r in t4:
        lines.append(
            f"| {r['seed']} | {r['name']} | {_fmt(r['ate_rmse_cm'], '.3f')} | {_fmt(r['psnr'])} | "
            f"{_fmt(r['ssim'], '.3f')} | {_fmt(r['lpips'], '.3f')} | {r['gaussians']} | "
            f"{_fmt(r['share_gaussians'], 'd')} | {_fmt(r['share_bytes'], 'd')} |"
        )
    lines += ["", f"Mean over {s.seeds} seed(s):", "",
              "| Method | ATE RMSE (cm) | PSNR | SSIM | LPIPS | Gaussians | Bytes shared |",
              "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name in dict.fromkeys(r["name"] for r in t4):
        group = [r for r in t4 if r["name"] == name]
        lines.append(
            f"| {name} | {_mean_cell(group, 'ate_rmse_cm', '.3f')} | {_mean_cell(group, 'psnr')} "
            f"| {_mean_cell(group, 'ssim', '.3f')} | {_mean_cell(group, 'lpips', '.3f')} | "
            f"{_mean_cell(group, 'gaussians', '.0f')} | {_mean_cell(group, 'share_bytes', '.0f')} |"
        )
    v = verdicts
    ate_text = (
        "ATE: a merge leaves B's poses as they were (compare ATE with --mode inject)."
        if s.mode == "merge"
        else f"On ATE in {v['pwas_beats_random_ate']} of {s.seeds}."
    )
    lines += [
        "",
        f"PWAS beats random at {s.budget}: on PSNR in {v['pwas_beats_random_psnr']} of "
        f"{s.seeds} seed(s). {ate_text}",
        "",
        "## Rate-distortion (B with A's share, mean over the sweep seeds)",
        "",
    ]
    if s.sweep_seeds == 0:
        lines.append("No sweep was run (`--sweep-seeds 0`).")
    else:
        lines += [
            "| Budget | Strategy | PSNR | ATE RMSE (cm) | Gaussians shared | Bytes shared |",
            "|---|---|---|---|---|---|",
        ]
    for budget in s.sweep:  # no rows without sweep seeds (_sweep_rows)
        for strategy in s.strategies:
            group = _sweep_rows(rows, s, budget, strategy)
            if group:
                lines.append(
                    f"| {budget} | {strategy} | {_mean_cell(group, 'psnr')} | "
                    f"{_mean_cell(group, 'ate_rmse_cm', '.3f')} | "
                    f"{_mean_cell(group, 'share_gaussians', '.0f')} | "
                    f"{_mean_cell(group, 'share_bytes', '.0f')} |"
                )
    if v["sweep"]:
        inject = s.mode == "inject"
        lines += [
            "",
            "PWAS minus random, paired by seed (mean ± standard error over the seeds; a mean "
            "within about two standard errors of 0 is not resolved by this many seeds):",
            "",
            "| Budget | Seeds | PSNR (dB) | PWAS higher |"
            + (" ATE RMSE (cm) | PWAS lower |" if inject else ""),
            "|---|---|---|---|" + ("---|---|" if inject else ""),
        ]
        for b in v["sweep"]:
            cells = [
                b["budget"], b["pairs"],
                _plus_minus(b["psnr_difference"], b["psnr_difference_se"], ".2f"),
                f"{b['pwas_higher_psnr']} of {b['pairs']}",
            ]  # fmt: skip
            if inject:
                cells += [
                    _plus_minus(b["ate_difference_cm"], b["ate_difference_se_cm"], ".3f"),
                    f"{b['pwas_lower_ate']} of {b['pairs']}",
                ]
            lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    lines += ["", "## Plots", ""]
    lines += [f"![{p.stem}]({p.relative_to(out)})" for p in plots]
    return "\n".join(lines) + "\n"


def _plot_rate_distortion(
    folder: Path,
    curves: dict[str, list[tuple[float, float | None, float | None]]],
    s: ExperimentSettings,
) -> Path:
    """PSNR and ATE of B against the share's bytes, one curve per strategy."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name, points in curves.items():
        x = [p[0] / 1e6 for p in points]
        full = name == "full"
        style = dict(marker="*", markersize=12, linestyle="none") if full else dict(marker="o")
        for ax, column in zip(axes, (1, 2), strict=True):
            ax.plot(x, [p[column] for p in points], label="A's full map" if full else name, **style)
    for ax, label in zip(axes, ("PSNR of agent B (dB)", "ATE RMSE of agent B (cm)"), strict=True):
        ax.set_xlabel("share size (MB; 0 = no share)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend()
    if s.mode == "merge":
        axes[1].set_title("a merge leaves B's poses as they were", fontsize="medium")
    fig.suptitle("Rate-distortion: B with A's share")
    fig.tight_layout()
    return _save(fig, folder / "rate_distortion.png")


def _plots(
    folder: Path, rows: list[dict[str, Any]], s: ExperimentSettings, full_log: Path
) -> list[Path]:
    """Rate-distortion curves, importance histogram and top-down importance map (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    paths = []

    curves = rate_distortion_curves(rows, s)
    if curves:  # none without a sweep (--sweep-seeds 0)
        paths.append(_plot_rate_distortion(folder, curves, s))

    with LogReader(full_log) as reader:
        gaussians = reader.read_map()
    scores = strategy_scores(gaussians, "pwas")
    assert s.keep is not None  # resolved from the config by run_experiment
    kept = np.sort(scores)[::-1][: max(1, round(s.keep * len(scores)))]
    fig, ax = plt.subplots(figsize=(6, 4))
    positive = scores[scores > 0]
    bins = list(log_edges(positive, 49))
    ax.hist(positive, bins=bins, alpha=0.6, label=f"all ({len(scores)})")
    ax.hist(kept[kept > 0], bins=bins, alpha=0.6, label=f"kept at {s.keep:g} ({len(kept)})")
    ax.set_xscale("log")
    ax.set_xlabel("PWAS importance")
    ax.set_ylabel("Gaussians")
    ax.set_title("Importance before and after pruning (unpruned run's map)")
    ax.legend()
    fig.tight_layout()
    paths.append(_save(fig, folder / "importance_hist.png"))

    plan = _plan_view(gaussians.means)
    fig, ax = plt.subplots(figsize=(6, 6))
    order = np.argsort(scores)
    shown = ax.scatter(plan[order, 0], plan[order, 1], c=np.log10(scores[order] + 1e-12), s=1,
                       cmap="turbo")  # fmt: skip
    fig.colorbar(shown, ax=ax, label="log10 PWAS importance")
    ax.set_aspect("equal")
    ax.set_title("Top-down view coloured by importance")
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    fig.tight_layout()
    paths.append(_save(fig, folder / "importance_topdown.png"))
    return paths


def _plan_view(means: np.ndarray) -> np.ndarray:
    """[N, 2] coordinates on the plane of the two largest principal axes (the floor plan).

    Indoor maps are wider than they are tall, so the axis of least spread is taken as up.
    """
    centred = means - means.mean(axis=0)
    _, _, vt = np.linalg.svd(centred[:: max(1, len(centred) // 20000)], full_matrices=False)
    return centred @ vt[:2].T


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
