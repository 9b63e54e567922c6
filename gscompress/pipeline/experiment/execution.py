"""How an experiment's runs are executed: one after another, or on a pool of worker processes,
each started once the logs it reads exist, reusing every run whose record matches its settings."""

from __future__ import annotations

import collections
import contextlib
import functools
import hashlib
import json
import logging
import multiprocessing
import os
import signal
import socket
import threading
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import (
    CancelledError,
    Future,
    ProcessPoolExecutor,
    ThreadPoolExecutor,
    wait,
)
from dataclasses import dataclass
from multiprocessing.queues import SimpleQueue
from pathlib import Path
from typing import Any, NoReturn

from gscompress import __version__
from gscompress.errors import GscError
from gscompress.io.codec import layout
from gscompress.io.files import abandoned_files, json_text, read_json, write_text_atomic
from gscompress.ops.merge import EXACT, MergeOptions
from gscompress.pipeline.experiment.protocol import FOR_B, ExperimentSettings, RunHandle
from gscompress.pipeline.share.options import ShareOptions
from gscompress.threads import use_threads

log = logging.getLogger(__name__)


class RunFailed(Exception):
    """A run that raised, after its retry: its message is the error, the traceback and the
    last lines the run logged. Not a GscError: the experiment reports it (results.md) and goes
    on with the runs that do not need it."""


@dataclass
class Record:
    """One step: its log, its settings key and what it reported (waited for when it runs in a
    worker process or on a cluster), or why it failed."""

    path: Path
    key: str
    _result: dict[str, Any] | None = None
    _future: Future[dict[str, Any]] | None = None
    _error: str | None = None

    def _settle(self) -> None:
        if self._result is None and self._error is None:
            assert self._future is not None
            try:
                self._result = self._future.result()
            except RunFailed as exc:
                self._error = str(exc)

    @property
    def result(self) -> dict[str, Any]:
        """What the run reported (waits for it); RunFailed if it failed."""
        self._settle()
        if self._error is not None:
            raise RunFailed(self._error)
        assert self._result is not None
        return self._result

    @property
    def error(self) -> str | None:
        """Why the run failed (waits for it), or None."""
        self._settle()
        return self._error


RETRIES = 1
"""How many times a failed run is started again before it is reported as failed."""


TAIL_LINES = 20
"""How many of a failed run's last log lines its report keeps."""


class _Tail(logging.Handler):
    """The last TAIL_LINES lines logged (a run's, for its failure report)."""

    def __init__(self) -> None:
        super().__init__()
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        self.lines: collections.deque[str] = collections.deque(maxlen=TAIL_LINES)

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record))


def run_job(job: Callable[[Path], dict[str, Any]], path: Path) -> dict[str, Any]:
    """`job(path)`, with any exception it raises turned into RunFailed carrying the error, its
    traceback and the run's last log lines (an interrupt goes through as it is)."""
    tail = _Tail()
    logger = logging.getLogger("gscompress")
    logger.addHandler(tail)
    try:
        return job(path)
    except Exception as exc:
        trace = traceback.format_exception(type(exc), exc, exc.__traceback__)
        text = "".join(trace[-3:]).rstrip()  # (the innermost frames and the error)
        lines = "\n".join(tail.lines)
        error = f"{type(exc).__name__}: {exc}"
        more = f"\nits last log lines:\n{lines}" if lines else ""
        raise RunFailed(f"{error}\n{text}{more}") from None
    finally:
        logger.removeHandler(tail)


def _score(log_path: Path, seq: Path, every: int, lpips: bool, device: str) -> dict[str, Any]:
    """`gsc eval` of a run on its own frames (without the per-frame list)."""
    from gscompress.pipeline.evaluate import evaluate_log
    from gscompress.pipeline.images import ImageOptions

    scores = evaluate_log(log_path, seq, ImageOptions(every=every, lpips=lpips, device=device))
    scores.pop("per_frame", None)
    return scores


def _slam_job(
    path: Path,
    seq: Path,
    config: Any,
    frames: str,
    inject: Path | None,
    s: ExperimentSettings,
    share_transform: Path | None = None,
) -> dict[str, Any]:
    from gscompress.pipeline.slam_run import slam_file
    from gscompress.pipeline.slam_run.options import SlamOptions

    options = SlamOptions(
        frames=frames, inject=inject, share_transform=share_transform, recording=s.recording
    )
    run = slam_file(seq, path, options, config=config, device=s.device, force=True)
    return {"slam": run, "eval": _score(path, seq, s.every, s.lpips, s.device)}


def _merge_job(
    path: Path,
    seq: Path,
    receiver: Path,
    share: Path | None,
    frames: str,
    seed: int,
    s: ExperimentSettings,
    share_transform: Path | None = None,
) -> dict[str, Any]:
    from gscompress.pipeline.merge import merge_logs

    merged = merge_logs(
        receiver,
        share,
        path,
        seq=seq,
        frames=frames,
        iters=s.merge_iters,
        views=s.merge_views,
        lr_final=s.merge_lr_final,
        device=s.device,
        seed=seed,
        share_transform=share_transform,
        merge=merge_options(s.merge_how),
        force=True,
    )
    return {"merge": merged, "eval": _score(path, seq, s.every, s.lpips, s.device)}


def _align_job(path: Path, source: Path, target: Path, seq: Path) -> dict[str, Any]:
    from gscompress.pipeline.align import align_agents

    # (refined on the receiver's own frames, which B has)
    return align_agents(source, target, path, true_transform(path), seq=seq)


def true_transform(estimated: Path) -> Path:
    """Where an align step writes the true transform, beside its estimate."""
    return estimated.with_name(f"{estimated.stem}_true{estimated.suffix}")


def merge_options(how: str) -> MergeOptions:
    """The merge an experiment's `merge_how` names: the exact concatenation, or `gsc merge`'s
    default."""
    return EXACT if how == "exact" else MergeOptions()


def _share_job(
    path: Path,
    source: Path,
    budget: str,
    options: ShareOptions,
    receiver: Path | None = None,
    device: str = "auto",
) -> dict[str, Any]:
    from gscompress.pipeline.share import share_log

    return share_log(source, path, budget, options, receiver=receiver, device=device, force=True)


def _rescore_job(
    path: Path, source: Path, seq: Path, sigma_d: float | None, device: str = "auto"
) -> dict[str, Any]:
    from gscompress.pipeline.score import score_file

    return score_file(source, path, seq, sigma_d=sigma_d, device=device, force=True)


def _reference_job(path: Path, source: Path, fmt: str) -> dict[str, Any]:
    from gscompress.pipeline.share.formats import format_share

    return format_share(source, path, fmt, force=True)


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
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    pids.put(os.getpid())
    use_threads(threads)
    threading.Thread(target=_end_with_parent, name="end-with-parent", daemon=True).start()


def _end_with_parent() -> None:
    """Wait for this process's parent to end, then end at once. A runner that ends normally
    has joined its workers before, so this only acts when it was killed; the run under way
    is cut, as the runner's own was (it keeps no record, so a rerun redoes it)."""
    parent = multiprocessing.parent_process()
    if parent is not None:
        parent.join()
        os._exit(1)


class Runner:
    """What every executor shares: the runs folder, each run's settings key, the records that
    let a rerun reuse finished runs, progress, retries and the report of a failed run.

    A subclass starts a run with `_start`, which returns a function that waits for its result
    (RunFailed when it failed); `_waiters`, when set, waits for each run on its own thread.
    """

    def __init__(
        self,
        seq: Path,
        out: Path,
        settings: ExperimentSettings,
        progress: Callable[[str, int, int], object] | None,
        total: int,
    ) -> None:
        self.seq, self.settings, self.progress, self.total = seq, settings, progress, total
        self.runs = out / "runs"
        self.runs.mkdir(parents=True, exist_ok=True)
        for unfinished in abandoned_files(self.runs):  # a killed runner's workers' (no record
            unfinished.unlink(missing_ok=True)  # points at them: their steps are redone)
        self.done = 0
        self.reused = 0
        self.failed: dict[str, str] = {}
        """Name and error of each run that failed (or was not run: a run it needs failed)."""
        self._lock = threading.Lock()
        self._waiters: ThreadPoolExecutor | None = None

    def close(self, cancel: bool) -> None:
        """Wait for the steps under way; with `cancel`, start no more."""
        if self._waiters is not None:
            self._waiters.shutdown(wait=True, cancel_futures=cancel)

    def _key(self, spec: dict[str, Any]) -> str:  # (of what a run is; _digest: of what it gave)
        text = json.dumps({"tool": __version__, **spec}, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def _start(
        self, name: str, job: functools.partial[dict[str, Any]], path: Path, after: Sequence[Record]
    ) -> Callable[[], dict[str, Any]]:
        """A function that runs `job(path)` once the steps in `after` are done (or waits for it
        to: an executor may start it at once, `after` passed on as its dependencies) and
        returns its result, or raises RunFailed. A second call is a second attempt."""
        raise NotImplementedError

    def _where(self, name: str) -> dict[str, Any]:
        """Where a run ran, for its record."""
        return {"host": socket.gethostname()}

    def _step(
        self,
        name: str,
        spec: dict[str, Any],
        job: functools.partial[dict[str, Any]],
        after: Sequence[RunHandle] = (),
        extra: Callable[[], dict[str, Any]] | None = None,
        suffix: str = ".mcap",
    ) -> Record:
        """Run `job(log path)` unless a record with the same key exists; `after`: the steps
        whose logs it reads; `extra()`: what the record adds to the job's result; `suffix`:
        of the file the job writes (a log, or an alignment's transform)."""
        path = self.runs / f"{name}{suffix}"
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
                return Record(path, key, saved["result"])
        needs = [step for step in after if isinstance(step, Record)]
        wait_for = self._start(name, job, path, needs)
        args = (name, record_path, spec, key, wait_for, needs, extra)
        if self._waiters is None:  # in this process: the steps it needs are done
            if self.progress is not None:
                self.progress(name, self.done, self.total)
            record = Record(path, key)
            try:
                record._result = self._run(*args)
            except RunFailed as exc:
                record._error = str(exc)
            return record
        return Record(path, key, _future=self._waiters.submit(self._run, *args))

    def _run(
        self,
        name: str,
        record_path: Path,
        spec: dict[str, Any],
        key: str,
        wait_for: Callable[[], dict[str, Any]],
        after: Sequence[Record],
        extra: Callable[[], dict[str, Any]] | None,
    ) -> dict[str, Any]:
        """Wait for a step, and start it again once if it fails; its record once done. A step
        fails unrun when a step it needs failed."""
        missing = [step.path.stem for step in after if step.error is not None]  # (waits)
        if missing:
            return self._failed(name, f"not run: it needs {', '.join(missing)}, which failed")
        attempts = 1 + RETRIES
        for attempt in range(attempts):
            try:
                result = wait_for()
                break
            except RunFailed as exc:
                if attempt + 1 == attempts:
                    log.error("run %s failed: %s", name, exc)
                    return self._failed(name, str(exc))
                log.warning("run %s failed; trying it again: %s", name, str(exc).split("\n")[0])
        result = {**result, **(extra() if extra else {})}
        record = {
            "key": key,
            "spec": spec,
            "result": result,
            "result_sha256": _digest(result),
            "ran_on": self._where(name),
        }
        write_text_atomic(record_path, json_text(record, indent=1))
        self._finished(name)
        return result

    def _failed(self, name: str, error: str) -> NoReturn:
        """Count a failed run done, and keep its error for the report."""
        with self._lock:
            self.failed[name] = error
        self._finished(name)
        raise RunFailed(error)

    def _finished(self, name: str) -> None:
        with self._lock:
            self.done += 1
            if self.progress is not None:
                self.progress(name, self.done, self.total)

    def slam(
        self,
        name: str,
        config: Any,
        frames: str,
        inject: RunHandle | None = None,
        align: RunHandle | None = None,
        transform: Path | None = None,
    ) -> Record:
        """A SLAM run on `frames`, evaluated on them (starting with the share `inject`, moved
        by the `transform` file of the step `align`)."""
        s = self.settings
        spec: dict[str, Any] = {
            "kind": "slam",
            "sequence": str(self.seq.resolve()),
            "config": config.to_dict(),
            "frames": frames,
            "inject": inject.key if inject else None,
            "every": s.every,
            "lpips": s.lpips,
        }
        if transform is not None and align is not None:
            spec["transform"] = {"align": align.key, "file": transform.name}
        if s.recording is not None:  # (a run of the recording's default topics keeps its key)
            spec["recording"] = s.recording.record()
        job = functools.partial(
            _slam_job,
            seq=self.seq,
            config=config,
            frames=frames,
            inject=inject.path if inject else None,
            s=s,
            share_transform=transform,
        )
        after = [r for r in (inject, align) if r is not None]
        return self._step(name, spec, job, after=after)

    def align(self, name: str, source: RunHandle, target: RunHandle) -> Record:
        """`source`'s map aligned to `target`'s, against their ground-truth first poses."""
        spec = {"kind": "align", "source": source.key, "target": target.key, "on_frames": True}
        job = functools.partial(_align_job, source=source.path, target=target.path, seq=self.seq)
        return self._step(name, spec, job, after=[source, target], suffix=".txt")

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
    ) -> Record:
        """Agent B with a share: merged into B's map and refined, or injected into a new run.

        With `share` None (merge mode only): B's map refined the same way without a share, the
        control that separates what the share brings from what the refinement brings. With
        `align` (anchor "own"), the share is moved by that step's estimated transform, or by
        the true one with `true`.
        """
        s = self.settings
        transform = None
        if align is not None and share is not None:
            transform = true_transform(align.path) if true else align.path
        if s.mode == "inject":  # its own name: both modes' runs can share one folder
            assert share is not None
            return self.slam(
                f"{name}_inject", config, frames, inject=share, align=align, transform=transform
            )
        spec: dict[str, Any] = {
            "kind": "merge",
            "receiver": receiver.key,
            "share": share.key if share else None,
            "frames": frames,
            "iters": s.merge_iters,
            "views": s.merge_views,
            "lr_final": s.merge_lr_final,
            "seed": seed,
            "every": s.every,
            "lpips": s.lpips,
            # (what the merge does: runs before it differ)
            "merge": merge_options(s.merge_how).record(),
        }
        if transform is not None:
            assert align is not None
            spec["transform"] = {"align": align.key, "true": true}
        job = functools.partial(
            _merge_job,
            seq=self.seq,
            receiver=receiver.path,
            share=share.path if share else None,
            frames=frames,
            seed=seed,
            s=s,
            share_transform=transform,
        )
        after = [receiver, share] if share else [receiver]
        after += [align] if transform is not None and align is not None else []
        return self._step(name, spec, job, after, extra=lambda: {"slam": receiver.result["slam"]})

    def share(
        self,
        name: str,
        source: RunHandle,
        budget: str,
        strategy: str,
        seed: int,
        receiver: RunHandle | None = None,
    ) -> Record:
        """A share of `source`'s map by `strategy`; with `receiver`, cut for that run (what its
        views do not draw first; `strategy` then ends in `FOR_B`, which the share drops)."""
        spec: dict[str, Any] = {
            "kind": "share",
            "source": source.key,
            "budget": budget,
            "strategy": strategy,
            "seed": seed,
        }
        if self.settings.fold:  # (unfolded steps keep the spec they always had)
            spec["fold"] = True
        if self.settings.spread:
            spec["spread"] = True
        if not self.settings.sums:
            spec["sums"] = False
        spec["ids"] = self.settings.ids
        spec["codec"] = layout()  # (a share's bytes follow it: one cut by another is not reused)
        if receiver is not None:
            spec["for"] = receiver.key
        job = functools.partial(
            _share_job,
            source=source.path,
            budget=budget,
            options=self.settings.share_options(strategy.removesuffix(FOR_B), seed),
            device=self.settings.device,
            receiver=None if receiver is None else receiver.path,
        )
        return self._step(name, spec, job, after=[source] + ([receiver] if receiver else []))

    def rescore(self, name: str, source: RunHandle, sigma_d: float | None) -> Record:
        """`source`'s map PWAS-scored again from its own frames at its own poses (`gsc score`,
        with `sigma_d`: None for the scene's, inf for no proximity weight)."""
        from gscompress.importance import sigma_d_value

        spec = {"kind": "rescore", "source": source.key, "sigma_d": sigma_d_value(sigma_d)}
        job = functools.partial(
            _rescore_job,
            source=source.path,
            seq=self.seq,
            sigma_d=sigma_d,
            device=self.settings.device,
        )
        return self._step(name, spec, job, after=[source])

    def reference(self, name: str, source: RunHandle, fmt: str) -> Record:
        """`source`'s whole map sent in the format `fmt` (`format_share`): a point of the
        field on the rate-distortion plot."""
        spec = {"kind": "reference", "source": source.key, "format": fmt}
        job = functools.partial(_reference_job, source=source.path, fmt=fmt)
        return self._step(name, spec, job, after=[source])

    def score(
        self,
        run: RunHandle,
        own: str,
        frames: dict[str, str],
        other: RunHandle | None = None,
        align: RunHandle | None = None,
    ) -> Record:
        """`run`'s map scored on A's frames, B's frames and all frames at refined poses
        (`gscompress.pipeline.experiment.cross_agent`), a step named after the run; `own`: the
        frame set of the agent that made the map ("a", "b", or "all"), `other`: the other
        agent's run, `align`: the alignment that moves its poses (anchor "own")."""
        from gscompress.pipeline.experiment.cross_agent import cross_scores

        s = self.settings
        spec = {
            "kind": "cross-score",
            "map": run.key,
            "own": own,
            "frames": frames,
            "other": other.key if other else None,
            "align": align.key if align else None,
            "iters": s.refine_poses,
            "every": s.every,
            "lpips": s.lpips,
            "all": "a and b",
        }
        job = functools.partial(
            cross_scores,
            seq=self.seq,
            log_path=run.path,
            own=own,
            frames=frames,
            other=other.path if other else None,
            transform=align.path if align else None,
            iters=s.refine_poses,
            every=s.every,
            lpips=s.lpips,
            device=s.device,
        )
        after = [r for r in (run, other, align) if r is not None]
        return self._step(f"{run.path.stem}_xeval", spec, job, after, suffix=".scores.json")


class LocalRunner(Runner):
    """Runs the steps of an experiment on this machine, reusing those whose records match.

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
        super().__init__(seq, out, settings, progress, total)
        self._stopping = threading.Event()
        self._pool: ProcessPoolExecutor | None = None
        self._worker_pids: SimpleQueue[int] | None = None
        jobs = min(jobs, total)  # no more workers than steps
        if jobs > 1:
            import torch

            available = torch.get_num_threads()
            threads = max(1, available // jobs)
            if threads * jobs != available:
                log.warning(
                    "%d torch threads do not split evenly over %d jobs: each run gets %d (%d in "
                    "all; see gsc --threads)",
                    available,
                    jobs,
                    threads,
                    threads * jobs,
                )
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
        super().close(cancel)
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=cancel)

    def _start(
        self, name: str, job: functools.partial[dict[str, Any]], path: Path, after: Sequence[Record]
    ) -> Callable[[], dict[str, Any]]:
        if self._pool is None:
            return functools.partial(run_job, job, path)

        def wait_for() -> dict[str, Any]:  # (on its waiting thread: the steps it reads are done)
            if self._stopping.is_set():
                raise CancelledError
            assert self._pool is not None
            future = self._pool.submit(run_job, job, path)
            while not wait([future], timeout=0.2).done:
                if self._stopping.is_set() and future.cancel():  # queued, not started
                    raise CancelledError
            return future.result()

        return wait_for
