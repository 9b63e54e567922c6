"""`gsc merge`: inject another agent's share into a receiver's map and refine it."""

from __future__ import annotations

import functools
from dataclasses import fields
from functools import partial
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from gscompress.ops.merge import RESOLVE, MergeOptions
from gscompress.pipeline import merge_logs
from gscompress.pipeline.merge import DEFAULT_REFINE_VIEWS
from gscompress.pipeline.refining import DEFAULT_LR_FINAL
from gscompress.slam.views import REFINE_VIEWS

from .options import (
    INPUT_FILE,
    F,
    FrameSubset,
    backend_option,
    check_recording_seq,
    codec_option,
    command_line,
    device_option,
    emit,
    force_option,
    icp_option,
    json_option,
    output_option,
    recording_options,
    refined_text,
    seed_option,
    seq_option,
    share_transform_option,
    size_option,
)
from .progress import Phases, progress_bar

MERGE_OPTIONS = tuple(field.name for field in fields(MergeOptions))
"""The options of `gsc merge` that `MergeOptions` holds, by the names of its fields."""


def _told_merge_options(f: F) -> F:
    """The options of `MergeOptions` (--align, --icp, --resolve, --voxel, --margin,
    --share-rate, --by-view, --footprint), passed to the command as one dict named `told` of
    those given on the command line: the rest as the merge chooses (`WITH_SENDER_VIEWS` for a
    share that carries keyframes)."""

    @functools.wraps(f)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        context = click.get_current_context()
        given = {name: kwargs.pop(name) for name in MERGE_OPTIONS}
        told = {
            k: v
            for k, v in given.items()
            if context.get_parameter_source(k) != ParameterSource.DEFAULT
        }
        return f(*args, told=told, **kwargs)

    return wrapper  # type: ignore[return-value]


@click.command("merge", short_help="Merge another agent's share into a map and refine it.")
@click.argument("receiver", metavar="RECEIVER.mcap", type=INPUT_FILE)
@click.argument("share", metavar="SHARE.mcap", type=INPUT_FILE)
@output_option("Output log (.mcap): the receiver's log with the merged, refined map.")
@seq_option(False, "The receiver's RGB-D sequence (to refine on; not needed with --iters 0).")
@recording_options
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
@click.option(
    "--align/--no-align",
    default=MergeOptions.align,
    show_default=True,
    help="Move the share onto the receiver's map where their surfaces overlap before merging: "
    "`gsc align`'s local step (coloured ICP on the opaque Gaussians' centres and colours, from "
    "where the share is; --icp).",
)
@icp_option
@click.option(
    "--resolve",
    type=click.Choice(RESOLVE),
    default=MergeOptions.resolve,
    show_default=True,
    help="Where both maps hold the same surface (a --voxel cell with Gaussians of both): keep "
    "the map whose Gaussians there were seen more by their own agent (evidence), always the "
    "receiver's, always the share's, or both (stack: the exact concatenation).",
)
@click.option(
    "--voxel",
    type=click.FloatRange(0.0, min_open=True),
    default=MergeOptions.voxel,
    show_default=True,
    help="Edge (m) of the cells that decide what is the same surface; also the farthest pair "
    "the alignment matches.",
)
@click.option(
    "--margin",
    type=click.FloatRange(1.0),
    default=MergeOptions.margin,
    show_default=True,
    help="With --resolve evidence, the share keeps a cell only where its evidence there is more "
    "than this many times the receiver's (the refinement sees the receiver's views, so a near "
    "tie goes to the receiver).",
)
@click.option(
    "--share-rate",
    type=click.FloatRange(0.0, 1.0),
    default=MergeOptions.share_rate,
    show_default=True,
    help="The share's Gaussians move at this fraction of the receiver's learning rates in the "
    "refinement (0: they keep the sender's values).",
)
@click.option(
    "--by-view/--no-by-view",
    default=MergeOptions.by_view,
    show_default=True,
    help="Let each of the share's Gaussians move at least at the fraction of its evidence "
    "that the receiver's views give it (what they see of it against what the sender's did).",
)
@click.option(
    "--footprint/--no-footprint",
    default=MergeOptions.footprint,
    show_default=True,
    help="With --resolve evidence, count a Gaussian's evidence in its cell only when its "
    "footprint (its 2-sigma ellipse) fits a cell face, so that a Gaussian larger than a cell, "
    "such as a fold of many, takes no cell from the other map's finer ones.",
)
@click.option(
    "--keyframes/--no-keyframes",
    default=True,
    show_default=True,
    help="Also refine on the sender's keyframes the share carries (`gsc share --keyframes`), "
    "at their poses moved as the share is; `gsc eval` of the result leaves those frames out.",
)
@device_option
@backend_option("the receiver log's `backend:`, auto")
@seed_option("Seed of the order of the refinement views.")
@share_transform_option
@codec_option(None, " [default: the receiver map's own codec]")
@force_option()
@json_option
@_told_merge_options
def merge(
    receiver: Path,
    share: Path,
    dst: Path,
    seq: Path | None,
    recording: Any,
    frames: object,
    size: tuple[int, int] | None,
    iters: int,
    views: str,
    lr_final: float,
    told: dict[str, Any],
    keyframes: bool,
    device: str,
    backend: str | None,
    seed: int,
    share_transform: Path | None,
    codec: str | None,
    force: bool,
    as_json: bool,
) -> None:
    """Merge SHARE.mcap (another agent's share) into the map of RECEIVER.mcap.

    Both maps must be in one world frame (agents anchored at the ground-truth pose of their
    first frame on one sequence are; else give --share-transform), yet they still sit
    centimetres apart, each map agreeing with its own trajectory. The merge:

    \b
    --align       moves the share onto the receiver where their surfaces overlap
                  (coloured ICP on the opaque Gaussians' centres, pairs at most
                  --voxel apart; the identity when they hardly overlap);
    --resolve     keeps, in each --voxel cell with Gaussians of both maps, only
                  one map's: the one whose agent saw them more (evidence: their
                  alpha*T sums, of those whose footprint fits a cell face;
                  the share's only above --margin times the receiver's), the
                  receiver's, or the share's (stack: both);
    refinement    on the receiver's own frames (--views) at its estimated poses
                  and on the sender's keyframes the share carries, if any,
                  a fresh optimizer, each view once per shuffled pass, the rates
                  decaying to --lr-final of the receiver's mapping rates; the
                  share's Gaussians move at --share-rate of them (0: they keep
                  the sender's values), or with --by-view at the fraction of
                  their evidence that the receiver's views give them.

    Every Gaussian kept has its id and PWAS sums (the share's ids move past the receiver's
    when they clash; the offset is reported). --no-align --resolve stack --share-rate 1
    --no-by-view is the exact concatenation, refined as one map. On office frag1 (A frames
    0-29, B 20-49, B receiving A's whole map, poses refined) the default rendered A's frames
    0.7 dB better than that and B's own 0.2 dB worse; docs/merge.md has every figure.
    A share that carries the sender's keyframes (`gsc share --keyframes`) is merged aligned
    and stacked, every Gaussian moving at the receiver's rates, on both agents' views (the
    options above, when given, change that): B receiving A's whole map and A's keyframes came
    within 0.5 dB of one agent mapping every frame, on both agents' frames of three sequences.
    `gsc eval` of the result leaves the carried frames out.
    `gsc slam --inject` is the other path: the share enters before the receiver maps, so its
    tracking benefits too (it is not aligned or resolved: the receiver has no map yet).

    \b
    Examples:
      gsc share a.mcap -o a_share.mcap --budget 0.2
      gsc merge b.mcap a_share.mcap --seq data/room -o b_merged.mcap
      gsc merge b.mcap a.mcap --seq data/room --no-align --resolve stack \\
          --share-rate 1 --no-by-view -o b_stacked.mcap
      gsc eval b_merged.mcap --seq data/room
      gsc share a.mcap -o a_views.mcap --budget 1 --keyframes 6 --seq data/room
      gsc merge b.mcap a_views.mcap --seq data/room -o b_merged.mcap
    """
    check_recording_seq(recording, seq)
    with progress_bar("merge", "step", hidden=as_json) as bar:
        phases = Phases(bar, {"refine": "iter"})
        phases("merging", 0, None)  # (reading, aligning, resolving: until the refinement)
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
            merge=told,
            keyframes=keyframes,
            recording=recording,
            command=command_line(),
            force=force,
            progress=partial(phases, "refine"),
        )
    emit(result, as_json, _merged_text(result, dst))


def _merged_text(result: dict[str, Any], dst: Path) -> str:
    """The line `gsc merge` prints of what it wrote."""
    text = (
        f"merged {result['share']} shared + {result['receiver']} own -> "
        f"{result['gaussians']} Gaussians in {dst}"
    )
    text += refined_text(result)
    if result.get("refine_carried_views"):
        text += f", {result['refine_carried_views']} of them the sender's keyframes"
    return text
