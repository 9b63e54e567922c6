"""`gsc score`: PWAS importance for an existing map from a sequence's views."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import click

from gscompress.pipeline import score_file

from .options import (
    INPUT_FILE,
    FrameSubset,
    SigmaD,
    backend_option,
    command_line,
    device_option,
    emit,
    force_option,
    json_option,
    output_option,
    recording_options,
    seq_option,
    size_option,
)
from .progress import advance, progress_bar


@click.command("score", short_help="PWAS-score a map made by any tool from a sequence.")
@click.argument("src", type=INPUT_FILE)
@seq_option()
@recording_options
@click.option(
    "--poses",
    type=INPUT_FILE,
    default=None,
    help="TUM trajectory of the views [default: a log's own estimated poses; for a PLY, or a "
    "log without poses, the sequence's ground truth].",
)
@click.option(
    "--frames",
    type=FrameSubset(),
    default=None,
    help="Views to score from: all, odd, even or START:STOP:STEP [default: a log's own "
    "subset, else all].",
)
@size_option(help="Render at this size WxH [default: a log's working size, else the sequence's].")
@click.option(
    "--sigma-d",
    type=SigmaD(),
    default="auto",
    show_default=True,
    help="Distance scale of the PWAS proximity weight, metres; auto: the median "
    "camera-to-surface distance of the first frame with valid depth (as gsc slam); inf: no "
    "proximity weighting.",
)
@device_option
@backend_option()
@output_option()
@force_option()
@json_option
def score(
    src: Path,
    seq: Path,
    recording: Any,
    poses: Path | None,
    frames: object,
    size: tuple[int, int] | None,
    sigma_d: float | None,
    device: str,
    backend: str,
    dst: Path,
    force: bool,
    as_json: bool,
) -> None:
    """Score every Gaussian of the map in SRC (.mcap log or 3DGS .ply) with PWAS.

    The map is rendered from each selected frame of SEQ (no optimisation) and each Gaussian's
    proximity-weighted alpha x transmittance is accumulated, so maps made by any 3DGS tool can
    be pruned and shared by importance. A gsc log is scored from its own estimated poses, frames
    and working size (as its run scored it) unless --poses, --frames or --size say otherwise.

    \b
    Examples:
      gsc score point_cloud.ply --seq data/office --size 320x240 -o scored.mcap
      gsc prune scored.mcap --keep 0.3 -o small.mcap
    """
    with progress_bar("score", "view", hidden=as_json) as bar:
        result = score_file(
            src,
            dst,
            seq,
            poses=poses,
            frames=None if frames is None else str(frames),
            size=size,
            sigma_d=sigma_d,
            backend=backend,
            device=device,
            command=command_line(),
            force=force,
            progress=partial(advance, bar),
            recording=recording,
        )
    emit(
        result,
        as_json,
        f"scored {result['scored']} of {result['gaussians']} Gaussians from "
        f"{result['views']} views -> {dst}",
    )
