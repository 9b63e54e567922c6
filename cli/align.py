"""`gsc align`: the rigid transform between two agents' world frames, from their maps."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from .options import (
    INPUT_FILE,
    OUTPUT_FILE,
    check_recording_seq,
    emit,
    force_option,
    icp_option,
    json_option,
    recording_options,
    seed_option,
    seq_option,
)
from .progress import Phases, progress_bar


@click.command("align", short_help="Estimate the transform between two maps' world frames.")
@click.argument("source", type=INPUT_FILE)
@click.argument("target", type=INPUT_FILE)
@click.option(
    "-o",
    "--output",
    "dst",
    type=OUTPUT_FILE,
    required=True,
    help="The transform file (.txt): a 4x4 matrix taking SOURCE's world frame to TARGET's, as "
    "--share-transform reads it.",
)
@click.option(
    "--init",
    type=INPUT_FILE,
    default=None,
    help="An initial guess of the transform (a --share-transform file); skips the global "
    "search and only refines it.",
)
@click.option(
    "--voxel",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Grid (m) of the global search's features [default: four times the median spacing "
    "of the maps' Gaussians].",
)
@click.option(
    "--min-overlap",
    type=click.FloatRange(0.0, 1.0),
    default=0.15,
    show_default=True,
    help="Refuse when neither map has this fraction of itself on the other once aligned.",
)
@seq_option(
    required=False,
    help="TARGET's sequence: refine the registration on TARGET's own frames, SOURCE's map "
    "rendered at 8 of TARGET's keyframes and moved until it draws them best where it covers "
    "them (the tracking loss, one rigid correction for all views). It corrects what geometry "
    "alone leaves loose, a flat table top turned by degrees. Needs torch; tens of seconds on "
    "a CPU.",
)
@recording_options
@icp_option
@seed_option("Seed of the global search (RANSAC).")
@force_option()
@json_option
def align(
    source: Path,
    target: Path,
    dst: Path,
    init: Path | None,
    voxel: float | None,
    min_overlap: float,
    seq: Path | None,
    recording: Any,
    icp: str,
    seed: int,
    force: bool,
    as_json: bool,
) -> None:
    """Estimate the rigid transform that maps SOURCE.mcap's world frame into TARGET.mcap's.

    For agents that each started at the identity where they were: the two maps (Gaussian
    centres with their colours, and normals) are registered by matching FPFH features under
    RANSAC, which needs no initial guess, then refined by coloured ICP (--icp). The overlap,
    the RMS residual of the overlapping part and the feature inliers are reported. An
    alignment that cannot be trusted is refused in one line (exit 1, no file): too little
    overlap, a symmetric scene where another transform fits nearly as well, or geometry that
    leaves a direction free (a plane, a cylinder). With --seq the result is then refined on TARGET's
    frames, and the frames also judge it: a registration whose only fault is too few agreeing
    feature matches is accepted when, refined, SOURCE's map draws TARGET's frames at most 2x
    as badly as TARGET's own map. The global step needs Open3D (pip install
    'gscompress[align]'); with --init only the local step runs, which needs no extra.

    \b
    Examples:
      gsc align a.mcap b.mcap -o a_to_b.txt
      gsc align a.mcap b.mcap -o a_to_b.txt --seq data/room   (refined on b's frames)
      gsc merge b.mcap a_share.mcap --share-transform a_to_b.txt --seq data/room -o m.mcap
      X
    """
    from gscompress.ops.align import AlignOptions
    from gscompress.pipeline.align import align_logs
    from gscompress.pipeline.aligning import ON_FRAMES

    check_recording_seq(recording, seq)
    options = AlignOptions(voxel=voxel, min_overlap=min_overlap, seed=seed, icp=icp)
    with progress_bar("align", "step", hidden=as_json) as bar:
        result = align_logs(
            source,
            target,
            dst,
            init=init,
            options=options,
            seq=seq,
            recording=recording,
            force=force,
            phases=Phases(bar, {ON_FRAMES: "iter"}),
        )
    T = result["T_target_source"]
    inliers = (
        ""
        if result["inliers"] is None
        else (f", {result['inliers']} feature inliers ({result['inlier_ratio']:.0%})")
    )
    text = (
        f"wrote {dst}: {Path(source).name} -> {Path(target).name}, translation "
        f"{[round(v, 4) for v in (T[0][3], T[1][3], T[2][3])]} m\n"
        f"overlap {result['overlap']:.0%}, residual {result['residual'] * 100:.2f} cm{inliers}, "
        f"ambiguity {result['ambiguity']:.2f}, conditioning {result['conditioning']:.3f}, "
        f"{result['seconds']:.2f} s"
    )
    if on_frames := result.get("on_frames"):
        from gscompress.pipeline.align import frames_text

        text += "\n" + frames_text(on_frames)
        ratio = on_frames["loss"] / on_frames["target_loss"] if on_frames["target_loss"] else None
        if ratio is not None and not on_frames.get("kept_registration"):
            text += f"; draws them at {ratio:.2f}x the target's own map's loss"
        if on_frames.get("overruled"):
            text += f"\naccepted on the frames; the registration alone: {on_frames['overruled']}"
    emit(result, as_json, text)
