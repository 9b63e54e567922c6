"""`gsc convert`: write a sequence (a folder or a recording) as a recording."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .options import (
    INPUT_SEQUENCE,
    emit,
    force_option,
    frames_option,
    json_option,
    recording_options,
    size_option,
)
from .progress import progress_bar

FORMATS = ("ros2", "ros2-sqlite", "ros1", "foxglove")
"""`gscompress.datasets.recording_writer.RECORDING_FORMATS`, named here for --help."""
COLOR_CODINGS = ("rgb8", "jpeg", "png")
DEPTH_CODINGS = ("32FC1", "16UC1", "compressedDepth")


def format_options(f: Any) -> Any:
    """--format, --color-encoding and --depth-encoding of a command that writes a recording."""
    f = click.option(
        "--depth-encoding",
        type=click.Choice(DEPTH_CODINGS),
        default="32FC1",
        show_default=True,
        help="Depth as 32FC1 metres (exact), 16UC1 millimetres (refused when depth is finer) or "
        "compressedDepth (a 16-bit PNG of millimetres; ROS formats only).",
    )(f)
    return click.option(
        "--color-encoding",
        type=click.Choice(COLOR_CODINGS),
        default="rgb8",
        show_default=True,
        help="Colour as raw rgb8 (exact), or a CompressedImage of JPEG (quality 95) or PNG.",
    )(f)


@click.command("convert", short_help="Write a sequence as a ROS 1/2 bag or a Foxglove MCAP.")
@click.argument("seq", type=INPUT_SEQUENCE)
@click.option(
    "-o",
    "--output",
    "out",
    required=True,
    type=click.Path(path_type=Path),
    help="The recording: a folder (ros2, ros2-sqlite), a .bag (ros1) or a .mcap (foxglove).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(FORMATS),
    default="ros2",
    show_default=True,
    help="ros2: a ROS 2 bag with MCAP storage; ros2-sqlite: with sqlite storage; ros1: a ROS 1 "
    "bag; foxglove: an MCAP of Foxglove schemas.",
)
@format_options
@frames_option
@size_option(help="Write at this size WxH [default: the sequence's own].")
@recording_options
@force_option()
@json_option
def convert(
    seq: Path,
    out: Path,
    fmt: str,
    color_encoding: str,
    depth_encoding: str,
    frames: object,
    size: tuple[int, int] | None,
    recording: Any,
    force: bool,
    as_json: bool,
) -> None:
    """Write the RGB-D sequence SEQ as a recording with the topics a RealSense camera (or a
    Foxglove app) records: colour, depth registered to it, camera info and, where SEQ has
    ground truth, /tf from `world` to `camera_color_optical_frame`.

    Raw colour and 32FC1 depth carry the frames bit for bit, so `gsc slam` of the recording
    maps as `gsc slam` of SEQ does.

    \b
    Examples:
      gsc convert room -o room_bag                      # ROS 2, MCAP storage
      gsc convert room -o room.bag --format ros1 --depth-encoding 16UC1
      gsc convert room -o room.mcap --format foxglove --color-encoding jpeg
    """
    from gscompress.pipeline.recordings import convert_sequence

    with progress_bar("convert", "frame", hidden=as_json) as bar:
        result = convert_sequence(
            seq,
            out,
            fmt,
            frames=str(frames),
            size=size,
            color=color_encoding,
            depth=depth_encoding,
            recording=recording,
            force=force,
            progress=bar.update,
        )
    emit(result, as_json, f"wrote {result['frames']} frames ({fmt}) to {out}")
