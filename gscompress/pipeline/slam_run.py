"""`gsc slam`: a sequence through the SLAM system into a log (`gscompress.io.mcap_log`).

A run starts fresh, from another agent's share (`inject`), or from the log of an interrupted
run (`resume`); the frame loop and the log it writes are the same in all three cases.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.datasets.base import enlargement_note, recorded_fingerprint, same_fingerprint
from gscompress.errors import (
    BudgetError,
    DatasetError,
    DivergenceError,
    InputError,
    LogFormatError,
    OptionError,
    OutputError,
    TrackingLostError,
)
from gscompress.io.codec import DEFAULT_CODEC, check_codec
from gscompress.io.decode_budget import DecodeBudget
from gscompress.io.files import check_output
from gscompress.io.mcap_log import (
    POSES_ESTIMATED,
    POSES_GROUND_TRUTH,
    TOPIC_CALIBRATION,
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    TOPIC_POSE_REFINED,
    TOPIC_STATS,
    LogMetadata,
    LogWriter,
    decode_pose,
    decode_snapshot,
    decode_trajectory,
    seconds_to_ns,
)
from gscompress.io.recover import (
    LogContents,
    Record,
    read_messages,
    resume_sources,
    unfinished_files,
)
from gscompress.pipeline.evaluate import check_first_frame
from gscompress.selection import check_ratio

log = logging.getLogger(__name__)

MIN_SIDE = 16
"""Smallest working image side `gsc slam` maps at."""

Progress = Callable[[int, int, dict[str, Any]], object]

Phases = Callable[[str, int, "int | None"], object]
"""A run's progress through its phases: called with (phase, steps done, steps in total)."""

FRAMES = "slam"
"""The phase of the frames (steps: frames), started before the first frame."""

FINAL_REFINEMENT = "final refinement"
"""The phase of the refinement after the last frame (steps: iterations)."""

FINAL_SCORING = "final scoring"
"""The phase of the finished map's PWAS scoring from every pose of the run (steps: views)."""


@dataclass
class _Run:
    """Everything the frame loop needs, however the run started."""

    config: Any  # SlamConfig
    sequence: Any  # RGBDSequence
    system: Any  # SlamSystem
    meta: LogMetadata
    inputs: list[str | Path]
    start: int = 0  # first processing position still to do
    carried: list[Record] = field(default_factory=list)  # messages of the resumed log
    est_poses: list[np.ndarray] = field(default_factory=list)
    gt_poses: list[np.ndarray] = field(default_factory=list)
    t_ns: int = 0
    leftovers: list[Path] = field(default_factory=list)  # unfinished files to delete at the end
    map_frames: int = 0  # the frames the log's latest map snapshot covers (where --resume starts)
    restart_map: Record | None = None  # a resumed finished log's last snapshot, not carried over
    codec: str = DEFAULT_CODEC  # of the map snapshots this run writes


def world_frame_of(sequence: Any, config: Any) -> str:
    """What a run's world frame is anchored to (see `LogMetadata.world_frame`)."""
    if config.init_from_ground_truth and sequence.has_ground_truth:
        return f"ground-truth:{sequence.name}"
    return f"first-camera:{sequence.name}:{int(sequence.indices[0])}"


def slam_file(
    seq: str | Path | None,
    dst: str | Path,
    *,
    preset: str | None = None,
    config_path: str | Path | None = None,
    frames: str | None = None,
    size: tuple[int, int] | None = None,
    device: str = "auto",
    backend: str | None = None,
    keep: float | None = None,
    no_prune: bool = False,
    inject: str | Path | None = None,
    share_transform: str | Path | None = None,
    resume: bool = False,
    config: Any = None,
    command: str = "",
    force: bool = False,
    progress: Progress | None = None,
    sequence: Any = None,
    codec: str = DEFAULT_CODEC,
    recording: Any = None,
    phases: Phases | None = None,
) -> dict[str, Any]:
    """Run SLAM over a sequence and write the log.

    The log holds the calibration, one `/camera/pose` (+ `/tf`) and `/slam/stats` record per
    frame, `/camera/pose_gt` where the sequence has ground truth, a `/gaussians` snapshot after
    each PWAS pruning stage, every `checkpoint_every` frames and at the end ("the map"), and the
    metadata record (full config, sequence, frames, world frame, command, results), written at
    the start and again at the end. Each frame is flushed to disk as soon as it is done.

    On KeyboardInterrupt or an exception the map so far is written as the final snapshot, the
    log is closed (valid and readable, results marked `interrupted`) and the exception is raised
    again. A run killed outright leaves its unfinished temporary file beside `dst`; `resume`
    continues from either.

    Args:
        seq: the sequence folder (None when `sequence` is given).
        dst: the output log (.mcap).
        preset: starting configuration (`gscompress.slam.config.PRESETS`; None: the config
            file's `preset:` entry, else `DEFAULT_PRESET`).
        config_path: a YAML config applied on top of the preset.
        frames: frame subset (all, odd, even, START:STOP:STEP; None: all).
        size: working size (W, H), overriding the config's.
        device: torch device, or "auto".
        backend: render backend (`gscompress.render.BACKENDS`), overriding the config's.
        keep: PWAS keep ratio of the pruning stages, overriding the config's.
        no_prune: skip the PWAS pruning stages (cyclic opacity cleanup still runs).
        inject: a share log whose Gaussians (with ids and PWAS sums) start the map; its world
            frame must be this run's, unless `share_transform` is given.
        share_transform: a file with the rigid transform from the share's world frame to this
            run's (4x4 or TUM `tx ty tz qx qy qz qw`).
        resume: continue the interrupted run whose log (or unfinished file) is at `dst`, with
            the config, frames and size recorded in it; the other options must be left unset.
        config: a ready `SlamConfig` to use instead of preset + `config_path` + options (which
            must then be left unset).
        command: the command line, for the metadata.
        force: overwrite `dst`.
        progress: called after every frame with (frames done, total, the frame's stats plus
            `seconds`, the wall time of this call's frames so far, the figure behind the
            result's `seconds_per_frame`).
        sequence: an already opened `RGBDSequence` (e.g. an in-memory synthetic one) instead
            of `seq`; `frames` and `size` are then not applied to it.
        codec: how the map snapshots are stored (`gscompress.io.codec.CODECS`); fp32, the
            default, is a foxglove.PointCloud that Foxglove draws.
        recording: a recording's `RecordingOptions` (topics, pairing, ground truth; None:
            chosen). The topics read are recorded in the log's results (`recording`), where
            `--resume` and the commands that reopen the log's sequence take them from.
        phases: called as the run goes through its phases, with (phase, steps done, steps
            in total): `FRAMES` once before the first frame (the frames a resumed log already
            holds as done), `FINAL_REFINEMENT` after each iteration of the refinement after the
            last frame, `FINAL_SCORING` after each view of the finished map's scoring.

    Returns:
        Output path, frame and Gaussian counts, seconds per frame, ATE (cm) when the sequence
        has ground truth, and whether the run was interrupted.
    """
    if sequence is None and seq is None:
        raise InputError("slam_file needs a sequence folder or an opened sequence")
    check_codec(codec)
    if keep is not None:
        check_ratio(keep, "--keep")
    if resume:
        given = {
            "--preset": preset,
            "--config": config_path or config,
            "--frames": frames,
            "--size": size,
            "--backend": backend,
            "--keep": keep,
            "--inject": inject,
            "--share-transform": share_transform,
        }
        clashing = [name for name, value in given.items() if value is not None]
        clashing += ["--no-prune"] if no_prune else []
        clashing += ["--rgb/--depth/--camera-info/--max-dt/--gt"] if _given(recording) else []
        if clashing:
            dropped = ", ".join(clashing)
            raise OptionError(f"--resume continues with the log's own settings; drop {dropped}")
        run = _resume_run(seq, dst, device, sequence)
    else:
        if config is None:
            from gscompress.slam.config import resolve_config

            config = resolve_config(
                preset, config_path, size=size, keep=keep, no_prune=no_prune, backend=backend
            )
        elif any(v is not None for v in (preset, config_path, size, keep, backend)) or no_prune:
            raise OptionError("a ready config takes no preset, config file or setting beside it")
        if share_transform is not None and inject is None:
            raise OptionError("a share transform needs --inject")
        run = _fresh_run(
            seq,
            dst,
            config,
            frames or "all",
            device,
            inject,
            share_transform,
            force,
            sequence,
            config_path,
            recording,
        )
    run.meta.command = command
    run.codec = codec
    return _loop(run, dst, progress, phases)


def check_working_size(intrinsics: Any) -> None:
    """Refuse a working size below `MIN_SIDE` a side (an OptionError: --size or a config's)."""
    w, h = intrinsics.width, intrinsics.height
    if min(w, h) < MIN_SIDE:
        raise OptionError(
            f"working size {w}x{h} is too small to map: SLAM needs at least {MIN_SIDE} pixels "
            "per side (--size, or the config's size)"
        )


def _given(recording: Any) -> bool:
    """Whether recording options other than the defaults were given."""
    return recording is not None and not recording.is_default


def _open(
    seq: str | Path | None, sequence: Any, config: Any, frames: str, recording: Any = None
) -> Any:
    """The sequence to run on, refusing an empty selection and a working size too small to map
    (below `MIN_SIDE`, pixels are so large that the map empties); warning when the working size
    enlarges the frames (the cpu preset's 160x120 on smaller images)."""
    from gscompress.datasets import open_sequence

    if sequence is None:
        assert seq is not None
        sequence = open_sequence(seq, size=config.size, frames=frames, recording=recording)
    name = getattr(sequence, "name", seq)
    if len(sequence) == 0:
        raise InputError(f"{name}: no frames selected ({frames})")
    k = sequence.intrinsics
    check_working_size(k)
    if note := enlargement_note(sequence):
        log.warning("%s", note)
    return sequence


def _fresh_run(
    seq: str | Path | None,
    dst: str | Path,
    config: Any,
    frames: str,
    device: str,
    inject: str | Path | None,
    share_transform: str | Path | None,
    force: bool,
    sequence: Any,
    config_path: str | Path | None,
    recording: Any = None,
) -> _Run:
    """A run from the first frame, optionally starting with another agent's share; no file
    it reads (sequence, config, share, transform) is written over. The unfinished file of a
    killed run of `dst` is, as an existing `dst` is, only with `force` (and once this run has
    written its log, so that a later --resume cannot pick the older run)."""
    from gscompress.slam.system import SlamSystem

    reads = (seq if sequence is None else None, config_path, inject, share_transform)
    inputs = [p for p in reads if p is not None]
    check_output(dst, inputs, force, ".mcap")
    unfinished = unfinished_files(dst)
    if unfinished and not force:
        raise OutputError(
            f"an unfinished run of {dst} is there ({unfinished[0].name}): continue it with "
            "--resume, or pass --force to start afresh (which removes it)"
        )
    sequence = _open(seq, sequence, config, frames, recording)
    system = SlamSystem(
        config, sequence.intrinsics, device, total_frames=len(sequence), frames=sequence.frame
    )
    meta = LogMetadata(
        config=config.to_dict(),
        sequence=sequence.name,
        frames=str(frames),
        world_frame=world_frame_of(sequence, config),
        # in the metadata written at the start, so that a killed run's file has it for --resume
        results={
            "first_frame": sequence.frame(0).fingerprint(),
            "poses": POSES_GROUND_TRUTH if config.tracking.use_ground_truth else POSES_ESTIMATED,
        },
    )
    if getattr(sequence, "choice", None) is not None:  # a recording: the topics it was read from
        from gscompress.datasets.recording import RecordingOptions, with_topics

        meta.results["recording"] = with_topics(
            recording or RecordingOptions(), sequence.choice
        ).record()
    if inject is not None:
        from gscompress.pipeline.merge import check_same_camera, read_share
        from gscompress.slam.keyframes import carried_views

        received = read_share(inject, meta.world_frame, "--inject", share_transform, True)
        record = received.record
        if received.carried:
            check_same_camera(
                received.camera,
                sequence.intrinsics,
                str(inject),
                "this run maps",
                "run at the sender's --size, or inject a share cut without --keyframes",
            )
        views = carried_views(received.carried, system.device)
        injected = system.receive(received.gaussians, views)
        operation = {
            "name": "inject",
            "gaussians": injected,
            "own_ids_from": system.own_ids_from,
            **record,
        }
        meta.provenance.append(
            {
                "operation": operation,
                "parent": record["share"],
                "parent_sha256": record["share_sha256"],
            }
        )
        meta.results["injected"] = injected
    return _Run(config, sequence, system, meta, inputs, leftovers=unfinished)


def _resume_run(seq: str | Path | None, dst: str | Path, device: str, sequence: Any) -> _Run:
    """A run restored from the log (or unfinished file) of an interrupted one at `dst`."""
    from gscompress.slam.config import SlamConfig
    from gscompress.slam.keyframes import View, in_views
    from gscompress.slam.system import SlamSystem

    dst = Path(dst)
    sources = resume_sources(dst)
    leftovers = [p for p in sources if p != dst]
    if not sources:
        raise InputError(f"--resume: there is no log {dst} nor an unfinished run of it")
    source, contents = _furthest(sources)
    meta = contents.metadata
    derived = len(_injections(meta.provenance)) < len(meta.provenance)  # (pruned, shared...)
    if any(step.get("carried_ns") for step in _injections(meta.provenance)):
        raise InputError(
            f"{dst} started with the keyframes of the share it received, which its log does "
            "not hold: run it afresh (--inject SHARE --force)"
        )
    if derived or ("frames" not in meta.results and contents.finished):
        raise InputError(f"{dst} is not the log of a `gsc slam` run (a share, prune or merge?)")
    if not meta.config:
        raise InputError(f"{source} records no SLAM config: not a `gsc slam` log")
    if contents.finished and not meta.results.get("interrupted", False):
        raise InputError(
            f"{dst} is a finished run of {meta.results['frames']} frames; nothing to resume"
        )
    config = SlamConfig.from_dict(meta.config)
    from gscompress.datasets.recording import RecordingOptions

    recorded = RecordingOptions.from_record(meta.results.get("recording"))
    sequence = _open(seq, sequence, config, meta.frames or "all", recorded)
    if meta.sequence and sequence.name != meta.sequence:
        raise InputError(f"{dst} was recorded on {meta.sequence!r}, not on {sequence.name!r}")
    found = check_first_frame(dst, meta.results.get("first_frame"), sequence)
    if recorded_fingerprint(meta.results.get("first_frame")) is None:  # (for later resumes)
        meta.results["first_frame"] = found

    by_topic: dict[str, list[Record]] = {}
    for record in contents.messages:
        by_topic.setdefault(record[1].topic, []).append(record)
    snapshots = by_topic.get(TOPIC_GAUSSIANS, [])
    stamps = [r[2].log_time for r in by_topic.get(TOPIC_POSE, [])]
    expected = [seconds_to_ns(t) for t in sequence.timestamps[: len(stamps)]]
    if len(stamps) > len(sequence) or stamps != expected:
        raise InputError(f"{dst}: its poses do not match the frames of {sequence.name}")

    # restore at the last snapshot: the frames up to its time are kept, later ones redone
    done, last = contents.map_frames(), snapshots[-1] if snapshots else None
    cut = stamps[done - 1] if done else -1
    carried = [
        r
        for r in contents.messages
        if r[1].topic == TOPIC_CALIBRATION or (done and r[2].log_time <= cut)
    ]
    restart_map = None
    if contents.finished and last is not None and _is_end_map(last, snapshots, by_topic):
        carried = [r for r in carried if r[2] is not last[2]]  # rewritten at the real end
        restart_map = last  # (or put back, if this run ends without a map of its own)

    system = SlamSystem(
        config, sequence.intrinsics, device, total_frames=len(sequence), frames=sequence.frame
    )
    run = _Run(config, sequence, system, meta, [seq] if seq is not None else [], start=done)
    run.carried, run.leftovers = carried, leftovers
    run.map_frames, run.restart_map = done, restart_map
    if done == 0:
        if _injections(meta.provenance):
            raise InputError(
                f"{dst} holds no map yet, so not the share it started with: run it afresh "
                "(--inject SHARE --force)"
            )
        run.carried = [r for r in carried if r[1].topic == TOPIC_CALIBRATION]
        return run
    assert last is not None
    budget = DecodeBudget("log", source.stat().st_size, str(source), LogFormatError)
    gaussians = decode_snapshot(last[0], last[2], str(source), budget).gaussians
    pose_records = by_topic[TOPIC_POSE][:done]
    stats = [_json(r) for r in by_topic.get(TOPIC_STATS, []) if r[2].log_time <= cut]
    poses = [decode_pose(r[0], r[2], str(source)) for r in pose_records]
    placed = _refined_at(by_topic, cut, done, str(source)) or poses
    kept = "frames" if system.keeps_every_view else "keyframes"
    views = [
        View.from_frame(position, sequence.frame(position), placed[position], system.device)
        for position in range(done)
        if in_views(position, kept, config.keyframes)
    ]
    next_id = max([s.get("next_id", 0) for s in stats] + [int(gaussians.ids.max()) + 1])
    system.restore(
        gaussians,
        [(int(sequence.indices[i]), float(sequence.timestamps[i]), poses[i]) for i in range(done)],
        views,
        mapping_iterations=sum(int(s.get("mapping_iters", 0)) for s in stats),
        next_id=next_id,
        first_depth=views[0].depth.cpu().numpy(),  # position 0 is always a keyframe
        own_ids_from=_own_ids_from(meta.provenance),
    )
    for frame_stats in stats:  # (the lost-track level as the interrupted run had it)
        system.track_level.add_error(frame_stats.get("tracking_depth_error", float("nan")))
    if sequence.has_ground_truth:
        _, gt = sequence.ground_truth()
        run.gt_poses, run.est_poses = list(gt[:done]), list(poses)
    run.t_ns = cut
    log.info("resuming %s after %d of %d frames", dst, done, len(sequence))
    return run


def _refined_at(
    by_topic: dict[str, list[Record]], cut: int, done: int, source: str
) -> list[np.ndarray] | None:
    """The refined trajectory of the first `done` frames as the log recorded it with its map
    at `cut` (None: the run refined no pose, or the log predates refined trajectories)."""
    records = [r for r in by_topic.get(TOPIC_POSE_REFINED, []) if r[2].log_time <= cut]
    if not records:
        return None
    trajectory = decode_trajectory(records[-1][0], records[-1][2], source)
    return list(trajectory) if len(trajectory) == done else None


def _furthest(sources: list[Path]) -> tuple[Path, LogContents]:
    """The file to resume from, with its contents: of the newest readable file's run (the same
    sequence, frames, config and first frame; a fresh `--force` run started since, or a run of
    another scene of the same name, is another run), the one whose last map covers the most
    frames, the newest on a tie. A resume killed in its turn leaves a file ahead of the log it
    started from. Raises the newest file's error if none reads."""
    best: tuple[int, Path, LogContents] | None = None
    first_error: LogFormatError | None = None
    run: tuple[Any, ...] | None = None
    for path in sorted(sources, key=lambda p: p.stat().st_mtime_ns, reverse=True):
        try:
            contents = read_messages(path)
        except LogFormatError as exc:
            first_error = first_error or exc
            continue
        meta = contents.metadata
        first = recorded_fingerprint(meta.results.get("first_frame"))
        if run is None:
            run = (meta.sequence, meta.frames, meta.config, first)
        same = (meta.sequence, meta.frames, meta.config) == run[:3] and (
            first is None or run[3] is None or same_fingerprint(first, run[3])
        )  # (a log from before the fingerprint, and its first resume's file, have one run)
        covered = contents.map_frames() if same else -1
        if best is None or covered > best[0]:
            best = (covered, path, contents)
    if best is None:
        assert first_error is not None
        raise first_error
    return best[1], best[2]


def _is_end_map(last: Record, snapshots: list[Record], by_topic: dict[str, list[Record]]) -> bool:
    """Whether a closed log's last snapshot is the map a run writes after its last whole frame
    (which the resumed run writes anew at its own end), rather than one a frame wrote (a
    pruning stage's or a checkpoint, which stays: a run stopped inside a frame writes no end
    map). The end map shares its time with its frame's stats record and, when that frame
    wrote a snapshot too, with that snapshot."""
    t = last[2].log_time
    if sum(1 for r in snapshots if r[2].log_time == t) > 1:
        return True
    stats = [_json(r) for r in by_topic.get(TOPIC_STATS, []) if r[2].log_time == t]
    return not any(s.get("event") for s in stats)


def _injections(provenance: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The injection steps (their operations) of a log's provenance."""
    steps = [p.get("operation", {}) for p in provenance]
    return [s for s in steps if s.get("name") == "inject"]


def _own_ids_from(provenance: list[dict[str, Any]]) -> int:
    """The `own_ids_from` an injection recorded in a log's provenance (0: none)."""
    return max([int(s.get("own_ids_from", 0)) for s in _injections(provenance)] + [0])


def _log_frame(run: _Run, out: LogWriter, frame: Any, result: Any, i: int) -> dict[str, Any]:
    """Write one processed frame: poses, stats, and a snapshot at a stage or checkpoint.

    Returns the frame's `/slam/stats` record.
    """
    total, every = len(run.sequence), run.config.checkpoint_every
    run.t_ns = seconds_to_ns(frame.timestamp)
    out.write_pose(result.T_world_cam, run.t_ns)
    if frame.T_world_cam is not None:
        out.write_pose(frame.T_world_cam, run.t_ns, ground_truth=True)
        run.gt_poses.append(frame.T_world_cam)
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


RESUMABLE = (DatasetError, OSError)
"""Errors partway through a run that `--resume` gets past once their cause is fixed (a frame
that cannot be read, a full disk)."""

RECURRING = (InputError, BudgetError, DivergenceError)
"""Errors partway through a run that come from its settings (a keep ratio too small, learning
rates too high for the data): a resume, which keeps them, would meet them again."""


def _write_refined(run: _Run, out: LogWriter) -> None:
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


def _json(record: Record) -> dict[str, Any]:
    import json

    value = json.loads(record[2].data)
    return value if isinstance(value, dict) else {}


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

    received = system.own_ids_from > 0
    if not system.config.pwas.final_scores or received or system.sigma_d is None:
        return gaussians
    log.debug("scoring the finished map from the run's %d views", len(system.poses))
    views = len(system.poses)
    step = None
    if phases is not None:
        phases(FINAL_SCORING, 0, views)
        step = _counter(functools.partial(phases, FINAL_SCORING), views)
    return score_map(
        gaussians,
        system.refined_poses(),
        system.intrinsics,
        sigma_d=system.sigma_d,
        backend=backend,
        device=system.device,
        progress=step,
    )


def _counter(report: Callable[[int, int], object], total: int) -> Callable[[Any], None]:
    """A callback that reports one more of `total` steps each time it is called."""
    done = itertools.count(1)

    def step(_: Any) -> None:
        report(next(done), total)

    return step


def _loop(
    run: _Run, dst: str | Path, progress: Progress | None, phases: Phases | None = None
) -> dict[str, Any]:
    """Process the frames from `run.start` on, writing the log as they are done."""
    from gscompress.importance import sigma_d_value
    from gscompress.metrics import ate_rmse_cm
    from gscompress.render import resolve_backend

    sequence, system, meta = run.sequence, run.system, run.meta
    total = len(sequence)
    failure: BaseException | None = None
    # resolved now so that a first-use kernel build is not timed; recorded with the timings
    backend = resolve_backend(run.config.backend, system.device)
    start = time.perf_counter()
    earlier = meta.results.pop("gaussians", None)  # (a resumed log's: its end map's count)
    meta.results.pop("error", None)
    with LogWriter(dst, meta, inputs=run.inputs, force=True) as out:
        if run.carried:
            for schema, channel, message in run.carried:
                out.copy_message(schema, channel, message)
        else:
            out.write_calibration(sequence.intrinsics, 0)
        out.write_metadata()
        out.flush()
        whole = True  # the map is the state after whole frames
        try:
            with _stop_between_frames(lambda: system.in_final_refinement) as stopping:
                system.stop_requested = stopping  # (for this run only: unset below)
                if phases is not None:
                    phases(FRAMES, run.start, total)
                    system.on_final_step = functools.partial(phases, FINAL_REFINEMENT)
                for i in range(run.start, total):
                    frame = sequence.frame(i)
                    whole = False
                    result = system.process(frame)
                    whole = True
                    stats = _log_frame(run, out, frame, result, i)
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
            system.stop_requested = system.on_final_step = None
        done = len(system.poses)
        gaussians = system.gaussian_map() if whole else None
        if gaussians is not None and failure is None and done == total:
            gaussians = _finished_scores(system, gaussians, backend, phases)  # (timed too)
        seconds = time.perf_counter() - start
        if gaussians is not None:  # else the last snapshot stands (see _stop_between_frames)
            out.write_gaussians(gaussians, run.t_ns, run.codec)
            _write_refined(run, out)
            meta.results["gaussians"] = len(gaussians)
            run.map_frames = done
        elif run.restart_map is not None and run.map_frames == run.start:
            out.copy_message(*run.restart_map)  # the map this run started from is still the last
            if earlier is not None:
                meta.results["gaussians"] = earlier
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
    for leftover in run.leftovers:
        leftover.unlink(missing_ok=True)
    if failure is not None:
        if isinstance(failure, TrackingLostError):  # (one line: what the log holds, what next)
            failure = TrackingLostError(
                failure.frame, failure.timestamp, failure.reason,
                f"{dst} holds the {done} frame(s) before it; to go on, map from there as a second "
                f"agent (gsc slam SEQ --frames {failure.frame}: -o next.mcap) and register the "
                f"two with gsc align next.mcap {dst}",
            )  # fmt: skip
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
    return {"output": str(dst), **meta.results}
