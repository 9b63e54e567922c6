"""`gsc convert` and the recording side of `gsc info`: a sequence written as a recording, and
what a recording holds (numpy, PIL, mcap and rosbags; never torch).

`mcap_kind(path)` tells the three kinds of MCAP file apart: a gscompress log (its metadata
record), a ROS 2 bag (header profile `ros2`) and a Foxglove recording (anything else).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from gscompress.datasets import RecordingOptions, open_sequence
from gscompress.datasets.recording import describe_recording
from gscompress.datasets.recording_writer import write_recording
from gscompress.errors import GscError, OutputError
from gscompress.io.files import is_within, resolved

GSC_LOG, ROS2_BAG, FOXGLOVE = "gscompress log", "ROS 2 bag (MCAP)", "Foxglove recording (MCAP)"


def mcap_kind(path: str | Path) -> str:
    """`GSC_LOG`, `ROS2_BAG` or `FOXGLOVE` for an MCAP file; a foreign MCAP that holds a map
    (`/gaussians`) counts as a log, as `gsc info` reads it as one.

    Raises:
        LogFormatError: not a readable MCAP (truncated, hostile sizes, ...).
    """
    from gscompress.io.mcap_log import TOPIC_GAUSSIANS, LogReader

    with LogReader(path) as reader:
        if reader.metadata.profile_version:
            return GSC_LOG
        if reader.profile == "ros2":
            return ROS2_BAG
        if any(c.topic == TOPIC_GAUSSIANS for c in reader.channels):
            return GSC_LOG
    return FOXGLOVE


def is_log(path: str | Path) -> bool:
    """True when `gsc info` reads `path` as a log (a map), False for a recording."""
    p = Path(path)
    if p.is_dir() or p.suffix.lower() in (".bag", ".db3"):
        return False
    if p.suffix.lower() != ".mcap":
        return True  # (not a recording: the log reader says what it is)
    return mcap_kind(p) == GSC_LOG


def recording_info(
    path: str | Path,
    options: RecordingOptions | None = None,
    error_text: Callable[[GscError], str] = str,
) -> dict[str, Any]:
    """What a recording holds (`gscompress.datasets.recording.describe_recording`): kind,
    topics with counts, sizes, encodings and rates, and the pair `gsc slam` would read (or
    why it would read none, the error as `error_text` says it)."""
    return describe_recording(Path(path), options, error_text)


def convert_sequence(
    seq: str | Path,
    out: str | Path,
    fmt: str = "ros2",
    *,
    frames: str = "all",
    size: tuple[int, int] | None = None,
    color: str = "rgb8",
    depth: str = "32FC1",
    recording: RecordingOptions | None = None,
    force: bool = False,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Write the sequence `seq` (a folder or a recording) as a recording `out` in `fmt`
    (`gscompress.datasets.recording_writer.RECORDING_FORMATS`).

    Returns:
        The output path, format, frame count and size.

    Raises:
        OutputError: `out` is the input or inside it, exists without `force`, or has the
            wrong suffix for `fmt`.
    """
    seq, out = Path(seq), Path(out)
    if resolved(out) == resolved(seq) or (seq.is_dir() and is_within(out, seq)):
        raise OutputError(f"output {out} is the input {seq} or inside it; choose another path")
    sequence = open_sequence(seq, size=size, frames=frames, recording=recording)
    try:
        write_recording(sequence, out, fmt, color, depth, force, progress)
    finally:
        close = getattr(sequence, "close", None)
        if close is not None:
            close()
    k = sequence.intrinsics
    return {
        "output": str(out),
        "format": fmt,
        "frames": len(sequence),
        "size": [k.width, k.height],
        "color": color,
        "depth": depth,
    }
