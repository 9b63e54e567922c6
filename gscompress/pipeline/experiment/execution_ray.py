"""An experiment's runs as Ray tasks: on an existing Ray cluster, or on a Ray instance started
on this machine.

Each run is one task that declares its CPUs (and one GPU where the runs render on CUDA); the
tasks it reads are passed to it as arguments, so that Ray starts it as soon as they have
finished, on whichever node has the resources free. Every node reads the sequence and writes
the logs at the same paths: the experiment folder and the sequence must be on storage that
every node sees (a shared filesystem). A task that fails (or whose worker or node is lost) is
started again once as a new task, on any node, then reported as failed. Ray is imported here
only, on first use.
"""

from __future__ import annotations

import functools
import logging
import math
import socket
from collections.abc import Callable, Sequence
from concurrent.futures import CancelledError, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from gscompress.errors import MissingDependencyError, OptionError
from gscompress.pipeline.experiment.execution import Record, RunFailed, Runner, run_job
from gscompress.pipeline.experiment.protocol import ExperimentSettings
from gscompress.threads import use_threads

log = logging.getLogger(__name__)


INSTALL_HINT = "the Ray executor needs Ray: pip install 'gscompress[cluster]'"


LOCAL_OBJECT_STORE_BYTES = 200 * 1024**2
"""Object store of a Ray instance started here: the tasks pass only their small results."""


def import_ray() -> Any:
    """The ray module, or MissingDependencyError with the install hint."""
    try:
        import ray
    except ImportError:
        raise MissingDependencyError(INSTALL_HINT) from None
    return ray


def _task(
    job: functools.partial[dict[str, Any]], path: Path, threads: int, *after: Any
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A run on a Ray worker with `threads` torch threads (as many threads as a local run's
    give the same numbers); its result, and the host and Ray node it ran on. `after`: the
    results of the tasks it reads (Ray starts it once they exist)."""
    import ray

    use_threads(threads)
    result = run_job(job, path)
    where = {"host": socket.gethostname(), "node": ray.get_runtime_context().get_node_id()}
    return result, where


class RayRunner(Runner):
    """Runs the steps of an experiment as Ray tasks, reusing those whose records match.

    Args:
        address: the cluster's address (`auto`: the one `ray start` on this machine joined, or
            RAY_ADDRESS; `HOST:PORT`: its head), or None to start Ray on this machine.
        cpus_per_run: CPUs each task declares, and its torch threads (rounded up).
        gpus_per_run: GPUs each task declares; None: one where the runs render on CUDA (the
            device is cuda, or auto on a cluster that has GPUs), else none.
    """

    def __init__(
        self,
        seq: Path,
        out: Path,
        settings: ExperimentSettings,
        progress: Callable[[str, int, int], object] | None,
        total: int,
        address: str | None = None,
        cpus_per_run: float = 1.0,
        gpus_per_run: float | None = None,
    ) -> None:
        if not (cpus_per_run > 0 and math.isfinite(cpus_per_run)):
            raise OptionError(
                f"`cpus_per_run` must be > 0, got {cpus_per_run}", options=("cpus_per_run",)
            )
        ray = import_ray()
        self._ray = ray
        self._own = not ray.is_initialized()
        if self._own:
            options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            if address is None:
                options["object_store_memory"] = LOCAL_OBJECT_STORE_BYTES
            try:
                ray.init(address=address, **options)
            except ConnectionError as exc:
                raise OptionError(
                    f"`address` {address}: no Ray cluster there ({exc})", options=("address",)
                ) from None
        if gpus_per_run is None:
            device = settings.device
            gpus = ray.cluster_resources().get("GPU", 0)
            on_cuda = device.startswith("cuda") or (device == "auto" and gpus > 0)
            gpus_per_run = 1.0 if on_cuda else 0.0
        self.resources = {"num_cpus": cpus_per_run, "num_gpus": gpus_per_run}
        nodes = [node["Resources"] for node in ray.nodes() if node.get("Alive")]
        if not any(
            r.get("CPU", 0) >= cpus_per_run and r.get("GPU", 0) >= gpus_per_run for r in nodes
        ):  # (Ray would wait for such a node for ever)
            if self._own:
                ray.shutdown()
            gpu = f" and {gpus_per_run:g} GPU" if gpus_per_run else ""
            raise OptionError(
                f"no node of the Ray cluster has {cpus_per_run:g} CPUs{gpu} for a run: lower "
                "`cpus_per_run`" + (" or run on `device` cpu" if gpu else ""),
                options=("cpus_per_run", "device"),
            )
        super().__init__(seq, out, settings, progress, total)
        self._threads = max(1, math.ceil(cpus_per_run))
        # a failed task is started again by Runner._run, as a new task (on any node): Ray's own
        # retries would print their notices on this process's standard output
        self._remote = ray.remote(max_retries=0, **self.resources)(_task)
        self._refs: dict[Path, Any] = {}
        self._where_ran: dict[str, dict[str, Any]] = {}
        self._retried: set[Path] = set()  # logs whose first task failed
        # one waiting thread per step: each writes its record once its task has finished
        self._waiters = ThreadPoolExecutor(max(1, total))
        log.info(
            "Ray: %s CPUs, %s GPUs in the cluster; each run takes %s",
            ray.cluster_resources().get("CPU", 0),
            ray.cluster_resources().get("GPU", 0),
            self.resources,
        )

    def close(self, cancel: bool) -> None:
        """Wait for the tasks under way (with `cancel`, cancel them: a SLAM run stops after
        its frame and keeps no record), then leave the cluster (or stop the Ray started here)."""
        if cancel:
            for ref in self._refs.values():
                self._ray.cancel(ref)
        super().close(cancel)
        if self._own:
            self._ray.shutdown()

    def _start(
        self, name: str, job: functools.partial[dict[str, Any]], path: Path, after: Sequence[Record]
    ) -> Callable[[], dict[str, Any]]:
        needs = [self._refs[step.path] for step in after if step.path in self._refs]
        self._refs[path] = self._remote.options(name=name).remote(job, path, self._threads, *needs)
        attempts = [0]

        def wait_for() -> dict[str, Any]:  # (once the steps in `after` have their results)
            while True:
                if attempts[0]:  # a new task, the tasks it reads done
                    ref = self._remote.options(name=name).remote(job, path, self._threads)
                    self._refs[path] = ref
                attempts[0] += 1
                try:
                    result, where = self._get(self._refs[path])
                except RunFailed:
                    if attempts[0] > 1:
                        raise
                    self._retried.add(path)
                    if not any(step.path in self._retried for step in after):
                        raise
                    continue  # a task it reads failed once, then made its log: not its failure
                self._where_ran[name] = where
                return result

        return wait_for

    def _get(self, ref: Any) -> Any:
        """A task's result; RunFailed if it failed (CancelledError if it was cancelled)."""
        exceptions = self._ray.exceptions
        try:
            return self._ray.get(ref)
        except exceptions.TaskCancelledError:
            raise CancelledError from None
        except exceptions.RayTaskError as exc:
            cause = exc.cause
            if isinstance(cause, RunFailed):
                raise RunFailed(str(cause)) from None
            raise RunFailed(f"{type(cause).__name__}: {cause}") from None
        except exceptions.RayError as exc:  # a worker or node lost, out of memory...
            raise RunFailed(f"{type(exc).__name__}: {exc}") from None

    def _where(self, name: str) -> dict[str, Any]:
        return self._where_ran.get(name, {})
