"""`gsc slam`: a sequence through the SLAM system into a log (`gscompress.io.mcap_log`).

A run starts fresh or from another agent's share (`slam_file`, with `inject`), or from the log of
an interrupted run (`resume_slam_file`): `gscompress.pipeline.slam_run.start`; the frame loop and
the log it writes (here) are the same in all three cases.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from gscompress.errors import (
    BudgetError,
    DatasetError,
    DivergenceError,
    InputError,
    OptionError,
    TrackingLostError,
)
from gscompress.io.codec import DEFAULT_CODEC, check_codec
from gscompress.io.mcap_log import LogWriter, seconds_to_ns
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.pipeline.slam_run.start import Run, fresh_run, resume_run

log = logging.getLogger(__name__)


Progress = Callable[[int, int, dict[str, Any]], object]

Phases = Callable[[str, int, "int | None"], object]
"""A run's progress through its phases: called with (phase, steps done, steps in total)."""

FRAMES = "slam"
"""The phase of the frames (steps: frames), started before the first frame."""

FINAL_REFINEMENT = "final refinement"
"""The phase of the refinement after the last frame (steps: iterations)."""

FINAL_SCORING = "final scoring"
"""The phase of the finished map's PWAS scoring from every pose of the run (steps: views)."""


def slam_file(
    seq: str | Path | None,
    dst: str | Path,
    options: SlamOptions | None = None,
    *,
    config: Any = None,
    device: str = "auto",
    codec: str = DEFAULT_CODEC,
    command: str = "",
    force: bool = False,
    progress: Progress | None = None,
    phases: Phases | None = None,
    sequence: Any = None,
) -> dict[str, Any]:
    """Run SLAM over a sequence and write the log.

    The log holds the calibration, one `/camera/pose` (+ `/tf`) and `/slam/stats` record per
    frame, `/camera/pose_gt` where the sequence has ground truth, a `/gaussians` snapshot after
    each PWAS pruning stage, every `checkpoint_every` frames and at the end ("the map"), and the
    metadata record (full config, sequence, frames, world frame, command, results), written at
    the start and again at the end. Each frame is flushed to disk as soon as it is done.

    On KeyboardInterrupt or an exception the map so far is written as the final snapshot, the
    log is closed (valid and readable, results marked `interrupted`) and the exception is raised
    again. A run killed outright leaves its unfinished temporary file beside `dst`;
    `resume_slam_file` continues from either.

    Args:
        seq: the sequence folder (None when `sequence` is given).
        dst: the output log (.mcap).
        options: what defines the run (`SlamOptions`: preset, config file, frames, size,
            keep ratio, backend, share, recording; None: the defaults).
        config: a ready `SlamConfig` to use instead of `options`' preset, config file and
            settings (which must then be left unset).
        device: torch device, or "auto".
        command: the command line, for the metadata.
        force: overwrite `dst`.
        progress: called after every frame with (frames done, total, the frame's stats plus
            `seconds`, the wall time of this call's frames so far, the figure behind the
            result's `seconds_per_frame`).
        sequence: an already opened `RGBDSequence` (e.g. an in-memory synthetic one) instead
            of `seq`; `options.frames` and `options.size` are then not applied to it.
        codec: how the map snapshots are stored (`gscompress.io.codec.CODECS`); fp32, the
            default, is a foxglove.PointCloud that Foxglove draws.
        phases: called as the run goes through its phases, with (phase, steps done, steps
            in total): `FRAMES` once before the first frame (the frames a resumed log already
            holds as done), `FINAL_REFINEMENT` after each iteration of the refinement after the
            last frame, `FINAL_SCORING` after each view of the finished map's scoring.

    Returns:
        Output path, frame and Gaussian counts, seconds per frame, ATE (cm) when the sequence
        has ground truth, and whether the run was interrupted.
    """
    options = SlamOptions() if options is None else options
    _check_options(seq, sequence, codec)
    options.check()
    config = _fresh_config(config, options)
    run = fresh_run(seq, sequence, dst, config, options, device, force)
    return _run(run, dst, command, codec, progress, phases)


def resume_slam_file(
    seq: str | Path | None,
    dst: str | Path,
    *,
    device: str = "auto",
    command: str = "",
    progress: Progress | None = None,
    sequence: Any = None,
    codec: str = DEFAULT_CODEC,
    phases: Phases | None = None,
) -> dict[str, Any]:
    """Continue the interrupted run whose log (or unfinished file) is at `dst`, with the config,
    frames, size, share and recording options recorded in it, through the frame loop of
    `slam_file` (the arguments of these names are its).

    Returns:
        As `slam_file`, with `resumed_at`: the frames the interrupted run had done.

    Raises:
        InputError: no log nor unfinished run at `dst`, or one that cannot be resumed (a
            finished run, a share or a pruned log, another sequence).
    """
    _check_options(seq, sequence, codec)
    run = resume_run(seq, dst, device, sequence)
    return _run(run, dst, command, codec, progress, phases)


def _run(
    run: Run,
    dst: str | Path,
    command: str,
    codec: str,
    progress: Progress | None,
    phases: Phases | None,
) -> dict[str, Any]:
    """A started run (fresh, injected or resumed) through its frames into `dst`."""
    run.meta.command = command
    run.codec = codec
    return _loop(run, dst, progress, phases)


def _check_options(seq: str | Path | None, sequence: Any, codec: str) -> None:
    """Refuse a run without a sequence and an unknown codec."""
    if sequence is None and seq is None:
        raise InputError("slam_file needs a sequence folder or an opened sequence")
    check_codec(codec)


RESUME_KEEPS = (
    "preset",
    "config",
    "frames",
    "size",
    "backend",
    "keep",
    "inject",
    "share_transform",
)
"""The settings a resume takes from the log, which may not be given beside it (as well as
`no_prune` and a recording's options), named as `gsc slam`'s options are (`config`: the config
file, `config_path`)."""


def refuse_own_settings(kept: tuple[Any, ...], no_prune: bool, recording: Any) -> None:
    """Refuse settings given beside `--resume` (`kept`: the values given of `RESUME_KEEPS`, in
    that order; None where not given), which `resume_slam_file` takes from the log.

    Raises:
        OptionError: naming the settings to drop.
    """
    clashing = [name for name, value in zip(RESUME_KEEPS, kept, strict=True) if value is not None]
    clashing += ["no_prune"] if no_prune else []
    shown = [f"`{name}`" for name in clashing]
    if _given(recording):
        recording_options = ("rgb", "depth", "camera_info", "max_dt", "gt")
        clashing += recording_options
        shown.append("/".join(f"`{name}`" for name in recording_options))
    if clashing:
        raise OptionError(
            f"`resume` continues with the log's own settings; drop {', '.join(shown)}",
            options=("resume", *clashing),
        )


def _fresh_config(config: Any, options: SlamOptions) -> Any:
    """The `SlamConfig` of a fresh run: `config` when given (with no setting beside it), else
    the preset's with the config file and the settings applied (`resolve_config`)."""
    o = options
    if config is None:
        from gscompress.slam.config import resolve_config

        return resolve_config(o.preset, o.config_path, **o.settings)
    if any(v is not None for v in (o.preset, o.config_path, o.size, o.keep, o.backend)) or (
        o.no_prune
    ):
        raise OptionError("a ready config takes no preset, config file or setting beside it")
    return config


def _given(recording: Any) -> bool:
    """Whether recording options other than the defaults were given."""
    return recording is not None and not recording.is_default


def _log_frame(run: Run, out: LogWriter, frame: Any, result: Any, i: int) -> dict[str, Any]:
    """Write one processed frame: poses, stats, and a snapshot at a stage or checkpoint.

    Returns the frame's `/slam/stats` record.
    """
    total, every = len(run.sequence), run.config.checkpoint_every
    run.t_ns = seconds_to_ns(frame.timestamp)
    out.write_pose(result.T_world_cam, run.t_ns)
    if frame.T_world_cam is not None:
        out.write_pose(frame.T_world_cam, run.t_ns, ground_truth=True)
        run.gt_poses.append(run.system.kept_poses.keep(frame.T_world_cam))
        run.est_poses.append(result.T_world_cam)
    stats = result.stats()
    checkpoint = every > 0 and (i + 1) % every == 0 and i + 1 < total
    if checkpoint and not result.event:
        stats["event"] = "checkpoint"
    out.write_stats(stats, run.t_ns)
    log.debug("frame %d of %d: %s", i + 1, total, stats)
    if result.event or checkpoint:
        out.write_gaussians(run.system.gaussian_map(), run.t_ns, run.codec)
        _write_refined(run, out)
        run.map_frames = i + 1
    out.flush()
    return stats


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's `malloc_trim`, or None where the C library has none (macOS, musl)."""
    try:
        return ctypes.CDLL(None).malloc_trim
    except (AttributeError, OSError):
        return None


def release_free_heap() -> None:
    """Hand the heap's free memory back to the system (glibc), as `gsc slam` does after each
    frame.

    The map is cut at each stage and regrows in tensors of other sizes, so freed space stays in
    the process as free heap; over a long run that slack, not live data, made the peak RSS grow
    with the frames (docs/recordings.md, "Streaming and memory"). Elsewhere a no-op.
    """
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


RESUMABLE = (DatasetError, OSError)
"""Errors partway through a run that `--resume` gets past once their cause is fixed (a frame
that cannot be read, a full disk)."""

RECURRING = (InputError, BudgetError, DivergenceError)
"""Errors partway through a run that come from its settings (a keep ratio too small, learning
rates too high for the data): a resume, which keeps them, would meet them again."""


def _write_refined(run: Run, out: LogWriter) -> None:
    """The trajectory as the mapping has refined it so far, beside each map snapshot (where a
    resume picks it up) and at the end (what the commands read), in runs that refine poses."""
    if run.config.poses.enabled and run.system.poses:
        out.write_trajectory(np.array(run.system.refined_poses()), run.t_ns)


def map_note(frames: int, map_frames: int) -> str:
    """What a log of `frames` frames whose last map covers `map_frames` of them leaves a
    resume to redo ("" when nothing)."""
    if map_frames >= frames:
        return ""
    if map_frames == 0:
        return " (but no map: a resume starts again from the first frame)"
    return f" (its last map covers the first {map_frames}: a resume redoes the rest)"


@contextlib.contextmanager
def _stop_between_frames(refining: Callable[[], bool]) -> Iterator[Callable[[], bool]]:
    """Let Ctrl-C and SIGTERM stop a run between frames; yields whether a stop was asked for,
    to check after each frame.

    A signal in the middle of a frame (say, while Gaussians are being removed) would leave the
    map half-updated and holding part of a frame whose pose is not logged; the map written at
    the end must be the state after whole frames, the one `--resume` restarts from. So the first
    signal is noted and the run stops after the frame; a second one stops at once, and then the
    end writes no map: the last snapshot stands (a checkpoint's, a pruning stage's, or the one a
    resumed run started from; `results.map_frames` says how many frames it covers). The final
    refinement after the last frame (minutes at full size on a CPU) polls the same flag and ends
    early, so the map written is the one refined so far (`refining` says when it runs, for the
    message). Only the main thread can take signals; elsewhere nothing changes.
    """
    pending: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return

    def note(signum: int, frame: object) -> None:
        if pending:
            raise KeyboardInterrupt
        pending.append(signum)
        if refining():
            log.warning(
                "ending the final refinement at the next iteration (again to stop at once, "
                "without writing the refined map)"
            )
        else:
            log.warning("stopping after this frame (again to stop at once)")

    previous = {s: signal.signal(s, note) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield lambda: bool(pending)
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _finished_scores(
    system: Any, gaussians: Any, backend: str, phases: Phases | None = None
) -> Any:
    """The finished map with its PWAS sums scored again from every pose of the run
    (`PwasConfig.final_scores`): what each Gaussian of the map as it ends draws in the run's
    views, not what it drew while the map was still growing. A run that received a share keeps
    its accumulated sums (they hold the sender's views), as does a run without valid depth
    (no sigma_d)."""
    from gscompress.ops.score import score_map
    from gscompress.slam.system import counted_steps

    received = system.own_ids_from > 0
    if not system.config.pwas.final_scores or received or system.sigma_d is None:
        return gaussians
    log.debug("scoring the finished map from the run's %d views", len(system.poses))
    views = len(system.poses)
    report = None
    if phases is not None:
        phases(FINAL_SCORING, 0, views)
        report = functools.partial(phases, FINAL_SCORING)
    return score_map(
        gaussians,
        system.refined_poses(),
        system.intrinsics,
        sigma_d=system.sigma_d,
        backend=backend,
        device=system.device,
        progress=counted_steps(views, report, release_free_heap),
    )


def _loop(
    run: Run, dst: str | Path, progress: Progress | None, phases: Phases | None = None
) -> dict[str, Any]:
    """Process the frames from `run.start` on, writing the log as they are done."""
    from gscompress.render import resolve_backend

    sequence, system, meta = run.sequence, run.system, run.meta
    total = len(sequence)
    # resolved now so that a first-use kernel build is not timed; recorded with the timings
    backend = resolve_backend(run.config.backend, system.device)
    start = time.perf_counter()
    earlier = meta.results.pop("gaussians", None)  # (a resumed log's: its end map's count)
    meta.results.pop("error", None)
    with LogWriter(dst, meta, inputs=run.inputs, force=True) as out:
        _write_start(run, out)
        failure, whole = _process_frames(run, out, progress, phases, start)
        done = len(system.poses)
        gaussians = system.gaussian_map() if whole else None
        if gaussians is not None and failure is None and done == total:
            gaussians = _finished_scores(system, gaussians, backend, phases)  # (timed too)
        seconds = time.perf_counter() - start
        _write_end_map(run, out, gaussians, earlier)
        _record_results(run, failure, whole, seconds, backend)
    for leftover in run.leftovers:
        leftover.unlink(missing_ok=True)
    if failure is not None:
        _raise_failure(failure, run, dst, done)
    return {"output": str(dst), **meta.results}


def _write_start(run: Run, out: LogWriter) -> None:
    """What a log holds before its frames: the resumed log's messages that are kept, or the
    calibration; and the metadata, flushed."""
    if run.carried:
        for schema, channel, message in run.carried:
            out.copy_message(schema, channel, message)
    else:
        out.write_calibration(run.sequence.intrinsics, 0)
    out.write_metadata()
    out.flush()


def _process_frames(
    run: Run, out: LogWriter, progress: Progress | None, phases: Phases | None, start: float
) -> tuple[BaseException | None, bool]:
    """Process and log the frames from `run.start` on until the last, or until a stop is asked
    for or an error stops them; the error or interrupt that stopped them (None: none) and
    whether the map is the state after whole frames.

    Raises:
        the error itself when it came before any frame was done (no log is better than an
        empty one).
    """
    sequence, system = run.sequence, run.system
    total = len(sequence)
    failure: BaseException | None = None
    whole = True  # the map is the state after whole frames
    try:
        with _stop_between_frames(lambda: system.in_final_refinement) as stopping:
            system.stop_requested = stopping  # (for this run only: unset below)
            system.release = release_free_heap  # (in refinements: docs/recordings.md)
            if phases is not None:
                phases(FRAMES, run.start, total)
                system.on_final_step = functools.partial(phases, FINAL_REFINEMENT)
            for i in range(run.start, total):
                frame = sequence.frame(i)
                whole = False
                result = system.process(frame)
                whole = True
                stats = _log_frame(run, out, frame, result, i)
                release_free_heap()  # (what the frame freed: docs/recordings.md)
                if progress is not None:
                    progress(i + 1, total, {**stats, "seconds": time.perf_counter() - start})
                if stopping():
                    raise KeyboardInterrupt
    except (KeyboardInterrupt, Exception) as exc:
        if len(system.poses) == run.start and not isinstance(exc, KeyboardInterrupt):
            raise  # nothing done: no log is better than an empty one
        failure = exc
        whole = whole or isinstance(exc, TrackingLostError)  # (lost before it changed the map)
    finally:
        system.stop_requested = system.on_final_step = system.release = None
    return failure, whole


def _write_end_map(run: Run, out: LogWriter, gaussians: Any, earlier: Any) -> None:
    """The map at the end (`gaussians`, None: the map is not the state after whole frames),
    with the refined trajectory; else the last snapshot stands (see `_stop_between_frames`),
    and a resumed run that ends where it started puts back the map it started from."""
    done = len(run.system.poses)
    meta = run.meta
    if gaussians is not None:  # else the last snapshot stands (see _stop_between_frames)
        out.write_gaussians(gaussians, run.t_ns, run.codec)
        _write_refined(run, out)
        meta.results["gaussians"] = len(gaussians)
        run.map_frames = done
    elif run.restart_map is not None and run.map_frames == run.start:
        out.copy_message(*run.restart_map)  # the map this run started from is still the last
        if earlier is not None:
            meta.results["gaussians"] = earlier


def _record_results(
    run: Run, failure: BaseException | None, whole: bool, seconds: float, backend: str
) -> None:
    """The run's results in its metadata: frames, timings, how it ended, ATE (cm) where the
    sequence has ground truth."""
    from gscompress.importance import sigma_d_value
    from gscompress.metrics import ate_rmse_cm

    system, meta = run.system, run.meta
    done, total = len(system.poses), len(run.sequence)
    meta.results.update(
        {
            "frames": done,
            "frames_total": total,
            "seconds": round(seconds, 3),
            "seconds_per_frame": round(seconds / max(done - run.start, 1), 4),
            "interrupted": failure is not None,
            "map_frames": run.map_frames,
            "device": str(system.device),
            "render_backend": backend,
            "sigma_d": sigma_d_value(system.sigma_d),
        }
    )
    if run.start:
        meta.results["resumed_at"] = run.start
    if failure is not None and not isinstance(failure, KeyboardInterrupt):
        meta.results["error"] = f"{type(failure).__name__}: {failure}"
    if isinstance(failure, TrackingLostError):
        meta.results["lost_at"] = {"frame": failure.frame, "timestamp": failure.timestamp}
    if len(run.gt_poses) >= 2:
        estimated = system.refined_poses() if whole else run.est_poses
        meta.results["ate_rmse_cm"] = ate_rmse_cm(
            np.array(run.gt_poses), np.array(estimated[: len(run.gt_poses)])
        )
        if run.config.poses.enabled:
            meta.results["ate_rmse_cm_tracked"] = ate_rmse_cm(
                np.array(run.gt_poses), np.array(run.est_poses)
            )


def _raise_failure(failure: BaseException, run: Run, dst: str | Path, done: int) -> NoReturn:
    """Raise what stopped the run, once its log is closed: a lost track with what the log holds
    and how to go on; an error its settings would meet again, or any other, with a warning of
    what the log holds."""
    if isinstance(failure, TrackingLostError):  # (one line: what the log holds, what next)
        failure = TrackingLostError(
            failure.frame,
            failure.timestamp,
            failure.reason,
            f"{dst} holds the {done} frame(s) before it; to go on, map from there as a second "
            f"agent (gsc slam SEQ --frames {failure.frame}: -o next.mcap) and register the "
            f"two with gsc align next.mcap {dst}",
        )
    elif isinstance(failure, RECURRING):
        log.warning(
            "%s holds the %d frame(s) done before the error; a resume would meet it again: "
            "run afresh with the settings changed (--force replaces the log)",
            dst,
            done,
        )
    elif not isinstance(failure, KeyboardInterrupt):  # (the caller says so for an interrupt)
        note = map_note(done, run.map_frames)  # (gsc slam says how to resume)
        log.warning("%s holds the %d frame(s) done before the error%s", dst, done, note)
    raise failure
