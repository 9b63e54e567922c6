"""How a `gsc slam` run starts: fresh, from another agent's share (`inject`), or from the log of
an interrupted run (`resume`); each gives the `Run` the frame loop goes on with
(`gscompress.pipeline.slam_run`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.datasets.base import enlargement_note, recorded_fingerprint, same_fingerprint
from gscompress.errors import InputError, LogFormatError, OptionError, OutputError
from gscompress.io.codec import DEFAULT_CODEC
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
from gscompress.pipeline.logs import check_first_frame, check_same_camera, read_share
from gscompress.pipeline.slam_run.options import SlamOptions

log = logging.getLogger(__name__)


MIN_SIDE = 16
"""Smallest working image side `gsc slam` maps at."""


@dataclass
class Run:
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


def check_working_size(intrinsics: Any) -> None:
    """Refuse a working size below `MIN_SIDE` a side (an OptionError: --size or a config's)."""
    w, h = intrinsics.width, intrinsics.height
    if min(w, h) < MIN_SIDE:
        raise OptionError(
            f"working size {w}x{h} is too small to map: SLAM needs at least {MIN_SIDE} pixels "
            "per side (`size`, or the config's size)",
            options=("size",),
        )


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


def fresh_run(
    seq: str | Path | None,
    sequence: Any,
    dst: str | Path,
    config: Any,
    options: SlamOptions,
    device: str,
    force: bool,
) -> Run:
    """A run from the first frame of the sequence, a folder `seq` (opened with `options`'
    frames and recording options) or an already opened `sequence`, optionally starting with
    another agent's share (`options.inject`); no file it reads (sequence, config, share,
    transform) is written over. The unfinished file of a killed run of `dst` is, as an
    existing `dst` is, only with `force` (and once this run has written its log, so that a
    later --resume cannot pick the older run)."""
    from gscompress.slam.system import SlamSystem

    frames, recording = options.frames or "all", options.recording
    inject, share_transform = options.inject, options.share_transform
    reads = (seq if sequence is None else None, options.config_path, inject, share_transform)
    inputs = [p for p in reads if p is not None]
    check_output(dst, inputs, force, ".mcap")
    unfinished = unfinished_files(dst)
    if unfinished and not force:
        raise OutputError(
            f"an unfinished run of {dst} is there ({unfinished[0].name}): continue it with "
            "`resume`, or pass `force` to start afresh (which removes it)",
            options=("resume", "force"),
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
        from gscompress.slam.keyframes import carried_views

        received = read_share(
            inject, meta.world_frame, "`inject`", share_transform, True, ("inject",)
        )
        record = received.record
        if received.carried:
            check_same_camera(
                received.camera,
                sequence.intrinsics,
                str(inject),
                "this run maps",
                "run at the sender's `size`, or inject a share cut without `keyframes`",
                ("size", "keyframes"),
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
    return Run(config, sequence, system, meta, inputs, leftovers=unfinished)


def resume_run(seq: str | Path | None, dst: str | Path, device: str, sequence: Any) -> Run:
    """A run restored from the log (or unfinished file) of an interrupted one at `dst`."""
    from gscompress.slam.config import SlamConfig
    from gscompress.slam.system import SlamSystem

    dst = Path(dst)
    sources = resume_sources(dst)
    leftovers = [p for p in sources if p != dst]
    if not sources:
        raise InputError(
            f"`resume`: there is no log {dst} nor an unfinished run of it", options=("resume",)
        )
    source, contents = _furthest(sources)
    meta = contents.metadata
    _check_resumable(dst, source, contents)
    config = SlamConfig.from_dict(meta.config)
    sequence = _open_resumed(seq, sequence, config, meta, dst)
    by_topic, stamps = _records_by_topic(contents, dst, sequence)

    # restore at the last snapshot: the frames up to its time are kept, later ones redone
    snapshots = by_topic.get(TOPIC_GAUSSIANS, [])
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
    run = Run(config, sequence, system, meta, [seq] if seq is not None else [], start=done)
    run.carried, run.leftovers = carried, leftovers
    run.map_frames, run.restart_map = done, restart_map
    if done == 0:
        if _injections(meta.provenance):
            raise InputError(
                f"{dst} holds no map yet, so not the share it started with: run it afresh "
                "(`inject` SHARE `force`)",
                options=("inject", "force"),
            )
        run.carried = [r for r in carried if r[1].topic == TOPIC_CALIBRATION]
        return run
    assert last is not None
    _restore(run, by_topic, last, cut, source)
    run.t_ns = cut
    log.info("resuming %s after %d of %d frames", dst, done, len(sequence))
    return run


def _check_resumable(dst: Path, source: Path, contents: LogContents) -> None:
    """Refuse to resume what is not an interrupted `gsc slam` run whose log holds what it
    started with (`source`: the file read, of `dst`'s run)."""
    meta = contents.metadata
    derived = len(_injections(meta.provenance)) < len(meta.provenance)  # (pruned, shared...)
    if any(step.get("carried_ns") for step in _injections(meta.provenance)):
        raise InputError(
            f"{dst} started with the keyframes of the share it received, which its log does "
            "not hold: run it afresh (`inject` SHARE `force`)",
            options=("inject", "force"),
        )
    if derived or ("frames" not in meta.results and contents.finished):
        raise InputError(f"{dst} is not the log of a `gsc slam` run (a share, prune or merge?)")
    if not meta.config:
        raise InputError(f"{source} records no SLAM config: not a `gsc slam` log")
    if contents.finished and not meta.results.get("interrupted", False):
        raise InputError(
            f"{dst} is a finished run of {meta.results['frames']} frames; nothing to resume"
        )


def _open_resumed(
    seq: str | Path | None, sequence: Any, config: Any, meta: LogMetadata, dst: Path
) -> Any:
    """The sequence of the run to resume, opened as it had it (frame subset, a recording's
    topics), checked to be the one it ran on (name and first frame)."""
    from gscompress.datasets.recording import RecordingOptions

    recorded = RecordingOptions.from_record(meta.results.get("recording"))
    sequence = _open(seq, sequence, config, meta.frames or "all", recorded)
    if meta.sequence and sequence.name != meta.sequence:
        raise InputError(f"{dst} was recorded on {meta.sequence!r}, not on {sequence.name!r}")
    found = check_first_frame(dst, meta.results.get("first_frame"), sequence)
    if recorded_fingerprint(meta.results.get("first_frame")) is None:  # (for later resumes)
        meta.results["first_frame"] = found
    return sequence


def _records_by_topic(
    contents: LogContents, dst: Path, sequence: Any
) -> tuple[dict[str, list[Record]], list[int]]:
    """The log's records by topic, and the log times of its poses, checked to be those of the
    sequence's first frames."""
    by_topic: dict[str, list[Record]] = {}
    for record in contents.messages:
        by_topic.setdefault(record[1].topic, []).append(record)
    stamps = [r[2].log_time for r in by_topic.get(TOPIC_POSE, [])]
    expected = [seconds_to_ns(t) for t in sequence.timestamps[: len(stamps)]]
    if len(stamps) > len(sequence) or stamps != expected:
        raise InputError(f"{dst}: its poses do not match the frames of {sequence.name}")
    return by_topic, stamps


def _restore(
    run: Run, by_topic: dict[str, list[Record]], last: Record, cut: int, source: Path
) -> None:
    """Restore the run's SLAM system as the log left it at its map `last` (log time `cut`,
    covering the first `run.start` frames): the map, the frames' poses and views (at the
    refined poses where the log has them), the mapping's counters and the lost-track level;
    and the frames' ground truth."""
    from gscompress.slam.keyframes import View, in_views

    system, sequence, config, done = run.system, run.sequence, run.config, run.start
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
        own_ids_from=_own_ids_from(run.meta.provenance),
    )
    for frame_stats in stats:  # (the lost-track level as the interrupted run had it)
        system.track_level.add_error(frame_stats.get("tracking_depth_error", float("nan")))
    if sequence.has_ground_truth:
        _, gt = sequence.ground_truth()
        run.gt_poses, run.est_poses = list(gt[:done]), list(poses)


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


def _json(record: Record) -> dict[str, Any]:
    import json

    value = json.loads(record[2].data)
    return value if isinstance(value, dict) else {}
