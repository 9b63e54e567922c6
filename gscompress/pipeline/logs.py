"""Helpers the command modules share for reading a log: its poses, the sequence it was made
from, its keyframes, rewriting its map, and reading a share.

A `gsc slam` run that refines poses (`PoseConfig`) logs both the pose each frame was tracked at
(`/camera/pose`) and the trajectory as the mapping refined it (`/camera/pose_refined`); the
commands use the refined one (`trajectory`) and say so. Logs without it, including every log
written before refined trajectories existed, give their tracked poses.

A log's poses are matched to its sequence's frames by time (`frames_with_poses`, the one lookup
of a pose per frame): a frame matches the pose whose log time is nearest to the frame's
timestamp in nanoseconds, when they differ by at most `POSE_MATCH_TOLERANCE_NS` (1 ms; `gsc
slam` writes the frame timestamp itself, so its logs match exactly, and frames of a 30 Hz camera
are 33 ms apart). A TUM trajectory's poses match within `TUM_MATCH_TOLERANCE_NS` (20 ms, the TUM
association's default, as its times come from another clock); `pose_source` reads either.

The log's keyframes are the frames its `/slam/stats` records mark as keyframes (`gsc slam`
writes one per frame); a log without those records gets every `keyframes.every`-th frame of its
config, counted over the frames that have a pose (`KEYFRAME_RULE`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.errors import InputError, LogFormatError
from gscompress.gaussians import GaussianMap
from gscompress.io.codec import check_codec
from gscompress.io.compact import COMPACT_DEFAULTS, CompactOptions
from gscompress.io.files import check_output, sha256
from gscompress.io.keyframes import CarriedFrame
from gscompress.io.mcap_log import (
    TOPIC_CALIBRATION,
    TOPIC_GAUSSIANS,
    TOPIC_POSE,
    TOPIC_STATS,
    LogMetadata,
    LogReader,
    LogWriter,
    Trajectory,
    seconds_to_ns,
)
from gscompress.io.trajectory import nearest_times, read_tum_trajectory
from gscompress.ops.merge import check_same_world

log = logging.getLogger(__name__)


def trajectory(reader: LogReader) -> Trajectory:
    """The log's camera trajectory (refined where it has one), logged as such when refined."""
    found = reader.read_trajectory()
    if found.refined:
        log.debug("%s: the %s trajectory", Path(reader.path).name, found.source)
    return found


# ---------------------------------------------------------------------------------------------
# A log's poses and its sequence

POSE_MATCH_TOLERANCE_NS = 1_000_000
"""Largest |log time - frame timestamp| (ns) at which a logged pose belongs to a frame."""


TUM_MATCH_TOLERANCE_NS = 20_000_000
"""Largest |trajectory time - frame timestamp| (ns) at which a TUM trajectory's pose belongs to a
frame (0.02 s, the default of TUM's association tool)."""


class Poses(NamedTuple):
    """The poses a file gives (`pose_source`).

    Attributes:
        times_ns: [N] int64 times.
        T_world_cam: [N, 4, 4] camera-to-world poses.
        tolerance_ns: how far a time may be from a frame's timestamp and still be its pose.
        trajectory: "refined" / "tracked" / "refined, then tracked" for a log's, "file" for a
            TUM trajectory's.
    """

    times_ns: np.ndarray
    T_world_cam: np.ndarray
    tolerance_ns: int
    trajectory: str


def pose_source(path: str | Path) -> Poses:
    """The poses a file gives: a log's trajectory (refined where it has one: `trajectory`),
    or a TUM trajectory's.

    Raises:
        LogFormatError: a log without `/camera/pose`, or unreadable.
        InputError: an unreadable or empty trajectory.
    """
    if Path(path).suffix.lower() == ".mcap":
        with LogReader(path) as reader:
            found = trajectory(reader)
        if len(found.times_ns) == 0:
            raise LogFormatError(
                f"{path} has no {TOPIC_POSE} messages (not a SLAM log): no poses to render at; "
                "give them with `poses` TRAJ.txt or `poses_from` OTHER.mcap",
                options=("poses", "poses_from"),
            )
        return Poses(found.times_ns, found.T_world_cam, POSE_MATCH_TOLERANCE_NS, found.source)
    tum = read_tum_trajectory(path)
    if len(tum) == 0:
        raise InputError(f"{path} holds no poses")
    times_ns = np.array([seconds_to_ns(t) for t in tum.timestamps], dtype=np.int64)
    return Poses(times_ns, tum.T_world_cam, TUM_MATCH_TOLERANCE_NS, "file")


def working_size(meta: LogMetadata) -> tuple[int, int] | None:
    """The working size (W, H) a log's run recorded in its config, or None (a share, whose
    config stays with the sender, or a run at the sequence's own size)."""
    recorded = meta.config.get("size")
    return (int(recorded[0]), int(recorded[1])) if recorded else None


def open_log_sequence(
    seq: str | Path,
    log_path: str | Path,
    meta: LogMetadata,
    frames: str | None = None,
    size: tuple[int, int] | None = None,
    recording: Any = None,
) -> Any:
    """The sequence a log was made from, opened as its run had it: the log's frame subset,
    working size and (a recording) topics unless given. Warns when the sequence is not the one
    the log names (its poses would then be compared with frames they do not belong to), and
    when the working size enlarges its frames.

    Raises:
        InputError: opened as the log's run had it, the sequence's first frame is not the one
            the log recorded (another scene under the same name).
    """
    from gscompress.datasets import RecordingOptions, open_sequence
    from gscompress.datasets.base import enlargement_note
    from gscompress.datasets.recording import is_recording

    recorded_size = working_size(meta)
    size = size or recorded_size
    subset = frames or meta.frames or "all"
    if (recording is None or recording.is_default) and is_recording(Path(seq)):
        recorded = RecordingOptions.from_record(meta.results.get("recording"))
        if recorded is not None and recorded.gt is not None and not recorded.gt.is_file():
            log.warning(
                "%s: the run's ground truth %s is gone; using the log's", log_path, recorded.gt
            )
            recorded = replace(recorded, gt=None)
        recording = recorded or recording
    sequence = open_sequence(seq, size=size, frames=subset, recording=recording)
    if meta.sequence and meta.sequence != sequence.name:
        log.warning(
            "%s was recorded from sequence %r, not %r", log_path, meta.sequence, sequence.name
        )
    as_recorded = subset == (meta.frames or "all") and list(size or []) == list(recorded_size or [])
    if as_recorded and len(sequence):  # (the first frame then is the one the run saw)
        check_first_frame(log_path, meta.results.get("first_frame"), sequence)
    if note := enlargement_note(sequence):
        log.warning("%s", note)
    return sequence


def check_first_frame(log_path: str | Path, recorded: Any, sequence: Any) -> list[float]:
    """The fingerprint of the sequence's first frame (`Frame.fingerprint`), checked against the
    one a log recorded of its own first frame (`results.first_frame`; older logs have none).

    Raises:
        InputError: they differ: the sequence is another scene (under the log's sequence name
            or another).
    """
    from gscompress.datasets.base import recorded_fingerprint, same_fingerprint

    found: list[float] = sequence.frame(0).fingerprint()
    recorded = recorded_fingerprint(recorded)
    if recorded is not None and not same_fingerprint(recorded, found):
        raise InputError(
            f"{log_path} was not recorded on this {sequence.name}: its first frame differs "
            f"(mean depth and colour {recorded} against {found})"
        )
    return found


def frames_with_poses(
    sequence: Any,
    pose_ns: np.ndarray,
    log_path: str | Path,
    tolerance_ns: int = POSE_MATCH_TOLERANCE_NS,
) -> tuple[np.ndarray, np.ndarray]:
    """The positions of the sequence's frames that have a pose (times `pose_ns`, from the file
    `log_path`) within `tolerance_ns` of their timestamp, and the index of each one's pose.

    Raises:
        InputError: no frame has one.
    """
    frame_ns = np.array([seconds_to_ns(t) for t in sequence.timestamps], dtype=np.int64)
    index = nearest_times(frame_ns, pose_ns, tolerance_ns)
    positions = np.flatnonzero(index >= 0)
    if len(positions) == 0:
        raise InputError(
            f"no frame of {sequence.name} has a pose in {log_path} within "
            f"{tolerance_ns / 1e6:g} ms: is this the sequence (and frame subset) the poses "
            "were made from?"
        )
    return positions, index[positions]


def carried_times(meta: LogMetadata, reader: LogReader | None = None) -> np.ndarray:
    """[K] int64 timestamps (ns) of the frames a share carried into this map and a merge
    refined it on (`carried_ns` of its provenance's merge steps), and, given the file's
    `reader`, of the keyframes it carries itself (a share's), sorted."""
    times: set[int] = set()
    if reader is not None:
        from gscompress.io.keyframes import TOPIC_KEYFRAME_POSE

        times.update(reader.read_poses(TOPIC_KEYFRAME_POSE)[0].tolist())
    for step in meta.provenance:
        operation = step.get("operation") if isinstance(step, dict) else None
        values = operation.get("carried_ns") if isinstance(operation, dict) else None
        if isinstance(values, list):
            times.update(int(t) for t in values if isinstance(t, int) and not isinstance(t, bool))
    return np.array(sorted(times), dtype=np.int64)


# ---------------------------------------------------------------------------------------------
# A log rewritten


def recorded_topics(parent: LogMetadata) -> dict[str, Any]:
    """The `recording` entry of a log's results (the topics, pairing tolerance and ground truth
    its run read a recording with), for the results of a log derived from it, so that
    reopening their sequence takes the same topics; {} when it has none."""
    value = parent.results.get("recording")
    return {} if value is None else {"recording": value}


def rewrite_map(
    src: str | Path,
    dst: str | Path,
    operation: dict[str, Any],
    transform: Callable[[GaussianMap], tuple[GaussianMap, dict[str, Any]]],
    *,
    codec: str | None = None,
    options: CompactOptions = COMPACT_DEFAULTS,
    command: str = "",
    force: bool = False,
    map_only: bool = False,
) -> dict[str, Any]:
    """Copy a log, replacing its map (the last snapshot) by `transform(map)`.

    Every other message passes through unchanged; with `map_only`, only the calibration does
    (no earlier snapshots, poses, stats or transforms: the file is as small as the map). The
    output's provenance gains `operation` and its results are what `transform` returns beside
    the new map. The new map is stored in `codec` (with `options` for compact), or None: in the
    codec of the one it replaces (an fp16 share stays fp16). The parent's recorded topics
    (`recorded_topics`) are carried into the results.
    """
    if codec is not None:
        check_codec(codec)
    check_output(dst, [src], force, ".mcap")
    with LogReader(src) as log_in:
        last = log_in.require_snapshots() - 1
        meta = log_in.metadata.derive(operation, src, command)
        inherited = recorded_topics(log_in.metadata)
        with LogWriter(dst, meta, inputs=[src], force=force) as out:
            snapshot = 0
            for schema, channel, message in log_in.iter_messages():
                if channel.topic != TOPIC_GAUSSIANS:
                    if not map_only or channel.topic == TOPIC_CALIBRATION:
                        out.copy_message(schema, channel, message)
                    continue
                if snapshot == last:
                    stored = log_in.decode_snapshot(schema, message)
                    new_map, results = transform(stored.gaussians)
                    meta.results = {**results, **inherited}
                    chosen = codec or stored.codec
                    meta.results["codec"] = chosen
                    out.write_gaussians(new_map, message.log_time, chosen, options)
                elif not map_only:
                    out.copy_message(schema, channel, message)
                snapshot += 1
    return {"output": str(dst), **meta.results}


def map_log(
    gaussians: GaussianMap,
    dst: str | Path,
    meta: LogMetadata,
    src: str | Path,
    results: dict[str, Any] | None = None,
    *,
    force: bool = False,
) -> dict[str, Any]:
    """A one-snapshot log of a map that came from `src` (`meta`: its metadata)."""
    meta.results = {
        "gaussians": len(gaussians),
        "scored": gaussians.has_importance,
        **(results or {}),
    }
    with LogWriter(dst, meta, inputs=[src], force=force) as out:
        out.write_gaussians(gaussians, 0)
    return {"output": str(dst), **meta.results}


# ---------------------------------------------------------------------------------------------
# A log's keyframes

KEYFRAME_RULE = (
    "the frames the log's /slam/stats records mark as keyframes; for a log without them, every "
    "keyframes.every-th frame of its config (the first always), counted over the frames that "
    "have a pose in the log"
)
"""Which frames are a log's keyframes (said in the commands' help)."""


def is_log_keyframe(
    position: int, log_time_ns: int, recorded: set[int] | None, config: Any
) -> bool:
    """Whether the frame at this position among those with a pose (log time `log_time_ns`) is
    one of the log's keyframes (`KEYFRAME_RULE`): one its stats mark (`recorded`, from
    `recorded_keyframes`), else every `keyframes.every`-th of `config` (a `SlamConfig`)."""
    from gscompress.slam.keyframes import is_keyframe

    if recorded is not None:
        return log_time_ns in recorded
    return is_keyframe(position, config.keyframes)


def keyframe_positions(
    pose_ns: np.ndarray, recorded: set[int] | None, config: dict[str, Any]
) -> list[int]:
    """Positions among a log's poses (log times `pose_ns`) of its keyframes (`KEYFRAME_RULE`;
    `recorded` from `recorded_keyframes`, `config` the log's recorded SLAM config), or every
    position when none is one. The SLAM config (and torch with it) is loaded only for a log
    whose stats mark no keyframes."""
    slam_config: Any = None
    if recorded is None:
        from gscompress.slam.config import DEFAULT_PRESET, SlamConfig, preset

        slam_config = SlamConfig.from_dict(config) if config else preset(DEFAULT_PRESET)
    return [
        i for i, t in enumerate(pose_ns) if is_log_keyframe(i, int(t), recorded, slam_config)
    ] or list(range(len(pose_ns)))


@dataclass(frozen=True)
class SpreadKeyframes:
    """Keyframes chosen evenly over a log (`spread_keyframes`).

    Attributes:
        times: their log times (ns).
        poses: their estimated camera-to-world poses.
        frames: their frames of the sequence (`gscompress.datasets.base.Frame`), or None
            when no sequence was given.
        intrinsics: the camera of those frames (the sequence's at the log's working size),
            else the log's calibration.
    """

    times: list[int]
    poses: list[np.ndarray]
    frames: list[Any] | None
    intrinsics: Any


def spread_keyframes(
    src: str | Path, count: int, seq: str | Path | None, purpose: str, recording: Any = None
) -> SpreadKeyframes:
    """Up to `count` of a log's keyframes (`KEYFRAME_RULE`) spread evenly from its first to its
    last, with their frames when `seq` is given (those with a frame in it; a recording read
    with `recording`'s topics, None: those the log's run recorded).

    Raises:
        InputError: the log has no poses; no keyframe is a frame of `seq`; no calibration
            (without `seq`). `purpose` names what needs them.
    """
    with LogReader(src) as reader:
        meta = reader.metadata
        found = trajectory(reader)
        pose_ns, poses = found.times_ns, found.T_world_cam
        keyframe_ns = recorded_keyframes(reader)
        intrinsics = reader.read_intrinsics()
    if len(pose_ns) == 0:
        raise InputError(f"{src} has no {TOPIC_POSE}: {purpose} needs the sender's poses")
    keyframes = keyframe_positions(pose_ns, keyframe_ns, meta.config)
    spread = np.linspace(0, len(keyframes) - 1, min(count, len(keyframes))).round()
    chosen = sorted({keyframes[int(k)] for k in spread})
    if seq is None:
        if intrinsics is None:
            raise InputError(
                f"{src} has no camera calibration: give `seq` to render at its size",
                options=("seq",),
            )
        times = [int(pose_ns[i]) for i in chosen]
        return SpreadKeyframes(times, [poses[i] for i in chosen], None, intrinsics)
    sequence = open_log_sequence(seq, src, meta, recording=recording)
    positions, pose_index = frames_with_poses(sequence, pose_ns, src)
    by_pose = {int(i): int(p) for p, i in zip(positions, pose_index, strict=True)}
    chosen = [i for i in chosen if i in by_pose]
    if not chosen:
        raise InputError(f"no keyframe of {src} is a frame of {sequence.name}")
    frames = [sequence.frame(by_pose[i]) for i in chosen]
    times = [int(pose_ns[i]) for i in chosen]
    return SpreadKeyframes(times, [poses[i] for i in chosen], frames, sequence.intrinsics)


def carried_keyframes(
    src: str | Path, count: int, seq: str | Path, recording: Any = None
) -> tuple[list[Any], Any]:
    """`count` of the log's keyframes spread over its run (`spread_keyframes`, `recording` as
    there) as a share carries them (`gscompress.io.keyframes.CarriedFrame`: the frame's
    timestamp, colour and depth at the log's working size, its estimated pose), and their
    camera.

    Raises:
        InputError: `count` outside 1..`MAX_CARRIED`, or as `spread_keyframes`.
    """
    from gscompress.io.keyframes import MAX_CARRIED, CarriedFrame
    from gscompress.io.mcap_log import seconds_to_ns

    if not 1 <= count <= MAX_CARRIED:
        raise InputError(f"`keyframes` is 1 to {MAX_CARRIED}, got {count}", options=("keyframes",))
    chosen = spread_keyframes(src, count, seq, "carrying keyframes", recording)
    assert chosen.frames is not None
    frames = [
        CarriedFrame(seconds_to_ns(f.timestamp), f.color, f.depth, np.asarray(T, np.float64))
        for f, T in zip(chosen.frames, chosen.poses, strict=True)
    ]
    return frames, chosen.intrinsics


def recorded_keyframes(reader: LogReader) -> set[int] | None:
    """The log times of the frames a log's `/slam/stats` records mark as keyframes, or None
    when it has no such records.

    Raises:
        LogFormatError: a stats record that is not a JSON object.
    """
    times: set[int] = set()
    seen = False
    for _schema, _channel, message in reader.iter_messages([TOPIC_STATS]):
        try:
            record = json.loads(message.data)
        except (json.JSONDecodeError, UnicodeDecodeError):
            record = None
        if not isinstance(record, dict):
            raise LogFormatError(f"{reader.path}: a {TOPIC_STATS} record is not a JSON object")
        if "keyframe" in record:
            seen = True
            if record["keyframe"] is True:
                times.add(int(message.log_time))
    return times if seen else None


# ---------------------------------------------------------------------------------------------
# A share as a receiver reads it


@dataclass(frozen=True)
class ReceivedShare:
    """A share as a receiver takes it (`read_share`).

    Attributes:
        gaussians: its map in the receiver's world frame.
        record: what a provenance step keeps of it (name, sha256, transform; `carried_ns`,
            the timestamps of the keyframes it carries, when it carries some and they were
            asked for).
        carried: the sender's keyframes it carries, at their poses in the receiver's world
            frame (when asked for).
        camera: the camera of those keyframes (None without any).
    """

    gaussians: GaussianMap
    record: dict[str, Any]
    carried: list[CarriedFrame]
    camera: Intrinsics | None


def read_share(
    share: str | Path,
    receiver_world: str,
    what: str,
    transform: str | Path | None = None,
    keyframes: bool = False,
    options: tuple[str, ...] = (),
) -> ReceivedShare:
    """A share's map in the receiver's world frame, what to record of it and, with `keyframes`,
    the keyframes it carries (`gscompress.io.keyframes`) moved alike. `what` names the receiving
    step in an error, and the parameters `options` (as `GscError`'s).

    Without `transform` the share's recorded world frame must be the receiver's; with it, the
    share is moved by the transform in the file (share frame -> receiver frame) instead.

    Raises:
        MapError: world frames unknown or different (without a transform).
        LogFormatError: keyframes that cannot be read (`read_carried`).
    """
    from gscompress.io.keyframes import read_carried
    from gscompress.io.trajectory import read_transform
    from gscompress.ops.merge import transform_map

    carried: list[CarriedFrame] = []
    camera: Intrinsics | None = None
    with LogReader(share) as share_log:
        shared = share_log.read_map()
        world = share_log.metadata.world_frame
        if keyframes:
            carried, camera = read_carried(share_log)
    record: dict[str, Any] = {"share": Path(share).name, "share_sha256": sha256(share)}
    if transform is None:
        check_same_world(receiver_world, world, what, options)
    else:
        T = read_transform(transform)
        shared = transform_map(shared, T)
        carried = [f.moved(T) for f in carried]
        record.update(share_world_frame=world, transform=np.round(T, 12).tolist())
    if carried:
        record["carried_ns"] = [f.time_ns for f in carried]
    return ReceivedShare(shared, record, carried, camera)


def check_same_camera(
    carried: Intrinsics | None,
    receiver: Intrinsics,
    share: Path | str,
    what: str,
    remedy: str,
    options: tuple[str, ...] = (),
) -> None:
    """Refuse keyframes taken with another camera (or size) than the receiver refines at: one
    refinement renders every view with one camera. `what` names the receiving step ("the
    merge refines"), `remedy` what the user can do instead, naming the parameters `options`
    (as `GscError`'s)."""
    if carried is None or not np.allclose(
        [carried.fx, carried.fy, carried.cx, carried.cy, carried.width, carried.height],
        [receiver.fx, receiver.fy, receiver.cx, receiver.cy, receiver.width, receiver.height],
        rtol=1e-3,
    ):
        got = "no camera" if carried is None else f"{carried.width}x{carried.height}"
        raise InputError(
            f"{share} carries keyframes of another camera ({got}) than the receiver's "
            f"{receiver.width}x{receiver.height} at which {what}: {remedy}",
            options=options,
        )
