"""`gsc merge`: inject another agent's share into a receiver's map and refine it."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import click

from gscompress.pipeline import merge_logs
from gscompress.pipeline.merge import DEFAULT_REFINE_VIEWS
from gscompress.pipeline.refine import DEFAULT_LR_FINAL
from gscompress.slam.views import REFINE_VIEWS

from .options import (
    INPUT_FILE,
    FrameSubset,
    advance,
    backend_option,
    codec_option,
    command_line,
    device_option,
    emit,
    force_option,
    json_option,
    output_option,
    progress_bar,
    refined_text,
    seed_option,
    seq_option,
    share_transform_option,
    size_option,
)


@click.command("merge", short_help="Merge another agent's share into a map and refine it.")
@click.argument("receiver", metavar="RECEIVER.mcap", type=INPUT_FILE)
@click.argument("share", metavar="SHARE.mcap", type=INPUT_FILE)
@output_option("Output log (.mcap): the receiver's log with the merged, refined map.")
@seq_option(False, "The receiver's RGB-D sequence (to refine on; not needed with --iters 0).")
@click.option(
    "--frames",
    type=FrameSubset(),
    default=None,
    help="The receiver's frames: all, odd, even or START:STOP:STEP [default: its log's subset].",
)
@size_option(help="Working size WxH [default: the receiver's config].")
@click.option(
    "--iters",
    type=click.IntRange(min=0),
    default=200,
    show_default=True,
    help="Refinement iterations on the receiver's views (0: concatenate only).",
)
@click.option(
    "--views",
    type=click.Choice(REFINE_VIEWS),
    default=DEFAULT_REFINE_VIEWS,
    show_default=True,
    help="Refine on every frame of the receiver (its --frames subset) or on its keyframes "
    "only (fewer views to load; 200 iterations on 5 keyframes overfit them).",
)
@click.option(
    "--lr-final",
    type=click.FloatRange(0.0, 1.0, min_open=True),
    default=DEFAULT_LR_FINAL,
    show_default=True,
    help="The refinement's learning rates (the receiver's mapping ones) decay geometrically to "
    "this fraction by its last iteration; 1 keeps them constant.",
)
@device_option
@backend_option("the receiver log's `backend:`, auto")
@seed_option("Seed of the order of the refinement views.")
@share_transform_option
@codec_option(None, " [default: the receiver map's own codec]")
@force_option()
@json_option
def merge(
    receiver: Path,
    share: Path,
    dst: Path,
    seq: Path | None,
    frames: object,
    size: tuple[int, int] | None,
    iters: int,
    views: str,
    lr_final: float,
    device: str,
    backend: str | None,
    seed: int,
    share_transform: Path | None,
    codec: str | None,
    force: bool,
    as_json: bool,
) -> None:
    """Merge SHARE.mcap (another agent's share) into the map of RECEIVER.mcap.

    Every Gaussian of both maps is kept with its parameters, id and PWAS sums (the share's ids
    move past the receiver's when they clash; the offset is reported). The merged map is then
    refined on the receiver's own frames (--views) at its estimated poses with a fresh optimizer,
    each view once per shuffled pass, its learning rates decaying to --lr-final of the
    receiver's mapping rates.
    Both maps must be in the same world frame (agents anchored at the ground-truth pose of
    their first frame on one sequence are). `gsc slam --inject` is the other path: the share
    enters before the receiver maps, so its tracking benefits too.

    \b
    Examples:
      gsc share a.mcap a_share.mcap --budget 0.2
      gsc merge b.mcap a_share.mcap --seq data/room -o b_merged.mcap
      gsc eval b_merged.mcap --seq data/room
    """
    with progress_bar("refine", "iter", total=iters, hidden=as_json) as bar:
        result = merge_logs(
            receiver,
            share,
            dst,
            seq=seq,
            frames=None if frames is None else str(frames),
            size=size,
            iters=iters,
            views=views,
            lr_final=lr_final,
            device=device,
            backend=backend,
            seed=seed,
            share_transform=share_transform,
            codec=codec,
            command=command_line(),
            force=force,
            progress=partial(advance, bar),
        )
    text = (
        f"merged {result['share']} shared + {result['receiver']} own -> "
        f"{result['gaussians']} Gaussians in {dst}"
    )
    text += refined_text(result)
    emit(result, as_json, text)
