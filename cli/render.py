"""`gsc render`: pictures of a log's map at the frames of its sequence."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import click

from gscompress.pipeline.images import COLORINGS

from .eval import images_text
from .options import (
    INPUT_FILE,
    backend_option,
    device_option,
    emit,
    force_option,
    json_option,
    recording_options,
    seq_option,
    view_options,
)
from .progress import advance, progress_bar


@click.command("render", short_help="Write PNGs of a map at its poses (rgb, importance, depth).")
@click.argument("src", metavar="LOG.mcap", type=INPUT_FILE)
@seq_option(help="The RGB-D sequence whose frames (and camera) to render at.")
@recording_options
@click.option(
    "-o",
    "--output",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder for the PNGs (made if missing).",
)
@view_options
@click.option(
    "--color",
    "colorings",
    type=click.Choice(COLORINGS),
    multiple=True,
    default=("rgb",),
    show_default=True,
    help="Colour the render by the map's colours, its PWAS importance or depth; repeat to "
    "write several.",
)
@click.option(
    "--side-by-side",
    is_flag=True,
    help="Also write one labelled figure per frame: observed | each colouring | error map.",
)
@backend_option()
@device_option
@force_option(more=" (the pictures in the folder)")
@json_option
def render(
    src: Path,
    seq: Path,
    recording: Any,
    out_dir: Path,
    view: dict[str, Any],
    colorings: tuple[str, ...],
    side_by_side: bool,
    backend: str,
    device: str,
    force: bool,
    as_json: bool,
) -> None:
    """Render the map of LOG at the frames of SEQ and write PNGs to a folder.

    Each colouring goes to its own subfolder, one PNG per frame named by its index in the
    sequence: rgb/ (the map as `gsc eval` scores it), importance/ (each Gaussian coloured by
    its PWAS importance on a log scale, viridis: where the Gaussians that decide the picture
    are), depth/ (rendered depth, magma). --side-by-side adds side_by_side/: the observed frame,
    the colourings and the error map in one figure with colour bars. The PSNR of the renders
    is printed as in `gsc eval`.

    \b
    Examples:
      gsc render run.mcap --seq data/room -o pictures --every 10
      gsc render run.mcap --seq data/room -o pictures --frames 40:41 --color rgb \\
          --color importance --side-by-side
      gsc render share.mcap --seq data/room -o pictures --poses-from run.mcap
    """
    from gscompress.pipeline.evaluate import evaluate_log
    from gscompress.pipeline.images import ImageOptions

    with progress_bar("render", "view", hidden=as_json) as bar:
        result = evaluate_log(
            src,
            seq,
            ImageOptions(
                **view,
                backend=backend,
                device=device,
                lpips=False,
                save_images=out_dir,
                force=force,
                colorings=colorings,
                side_by_side=side_by_side,
            ),
            progress=partial(advance, bar),
            recording=recording,
        )
    summary = {k: result[k] for k in ("log", "sequence", "frames", "poses", "psnr", "images")}
    psnr = "unavailable" if result["psnr"] is None else f"{result['psnr']:.2f} dB"
    text = (
        f"{src} at {result['frames_evaluated']} frame(s) of {result['sequence']} "
        f"(PSNR {psnr}): {images_text(result['images'])}"
    )
    emit(summary, as_json, text)
