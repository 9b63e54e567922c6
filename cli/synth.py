"""`gsc synth`: write the embedded synthetic RGB-D sequence (TUM layout) for demos and tests."""

from __future__ import annotations

from pathlib import Path

import click

from gscompress.datasets.synthetic import write_synthetic_sequence

from .convert import FORMATS, format_options
from .options import (
    emit,
    force_option,
    json_option,
    output_path,
    seed_option,
    size_option,
)
from .progress import progress_bar


@click.command("synth", short_help="Make a synthetic RGB-D room sequence with ground truth.")
@click.argument("out_dir", type=click.Path(path_type=Path), required=False)
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    metavar="OUT_DIR",
    default=None,
    help="The sequence folder (or recording) to write, as the other commands take it; or give "
    "it as OUT_DIR.",
)
@click.option(
    "--frames", type=click.IntRange(1, 100_000), default=60, show_default=True, help="Frame count."
)
@size_option(default="320x240", help="Image size WxH.")
@seed_option(help="Scene seed.")
@click.option(
    "--supersample",
    type=click.IntRange(1, 4),
    default=1,
    show_default=True,
    help="Colour samples per pixel along each axis (2 = 2x2 anti-aliasing, about 2x slower).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(("tum", *FORMATS)),
    default="tum",
    show_default=True,
    help="tum: a TUM folder; ros2, ros2-sqlite, ros1, foxglove: a recording (as `gsc convert` "
    "writes), its depth exact.",
)
@format_options
@force_option()
@json_option
def synth(
    out_dir: Path | None,
    output: Path | None,
    frames: int,
    size: tuple[int, int],
    seed: int,
    supersample: int,
    fmt: str,
    color_encoding: str,
    depth_encoding: str,
    force: bool,
    as_json: bool,
) -> None:
    """Render a textured synthetic room with exact depth and ground-truth poses to -o OUT_DIR.

    Writes rgb/, depth/ (uint16, 5000 per metre), rgb.txt, depth.txt, groundtruth.txt and
    intrinsics.json; `gsc slam OUT_DIR` and any TUM reader open it. Same seed, same bytes.
    --force replaces an earlier sequence, never a folder that holds other files. With --format
    ros2|ros2-sqlite|ros1|foxglove, OUT_DIR is a recording instead (see `gsc convert`), its
    depth the exact rendered depth (32FC1).

    \b
    Examples:
      gsc synth -o room                             # 60 frames, 320x240
      gsc synth -o room_small --frames 40 --size 160x120 --supersample 2
      gsc slam room -o room.mcap                    # then map it
      gsc synth -o room_bag --format ros2           # the same room as a ROS 2 bag
    """
    out_dir = output_path(out_dir, output, "sequence", "OUT_DIR")
    if fmt != "tum":
        from gscompress.datasets.recording_writer import write_recording
        from gscompress.datasets.synthetic import synthetic_sequence

        sequence = synthetic_sequence(frames, size, seed, supersample)
        with progress_bar("synth", "frame", total=frames, hidden=as_json) as bar:
            write_recording(
                sequence, out_dir, fmt, color_encoding, depth_encoding, force, bar.update
            )
        text = f"wrote {frames} frames ({size[0]}x{size[1]}, {fmt}) to {out_dir}"
        emit(_result(out_dir, frames, size, fmt), as_json, text)
        return
    with progress_bar("synth", "frame", total=frames, hidden=as_json) as bar:
        out = write_synthetic_sequence(
            out_dir,
            frames=frames,
            size=size,
            seed=seed,
            force=force,
            progress=bar.update,
            supersample=supersample,
        )
    text = f"wrote {frames} frames ({size[0]}x{size[1]}) to {out}"
    emit(_result(out, frames, size, fmt), as_json, text)


def _result(out: Path, frames: int, size: tuple[int, int], fmt: str) -> dict[str, object]:
    """What --json prints."""
    return {"output": str(out), "frames": frames, "size": list(size), "format": fmt}
