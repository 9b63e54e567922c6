"""`gsc prune`: keep the most important fraction of a log's map."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from gscompress.io.compact import CompactOptions
from gscompress.pipeline import prune_log
from gscompress.selection import STRATEGIES

from .options import (
    INPUT_FILE,
    Ratio,
    check_recording_seq,
    codec_option,
    command_line,
    emit,
    fold_option,
    force_option,
    json_option,
    log_refiner,
    map_refine_options,
    map_sums_option,
    output_option,
    refined_text,
    seed_option,
)
from .progress import Phases, progress_bar


@click.command("prune", short_help="Keep the highest-scoring fraction of a log's map.")
@click.argument("src", type=INPUT_FILE)
@click.option(
    "--keep",
    type=Ratio(),
    required=True,
    help="Fraction of Gaussians to keep, in (0, 1] (e.g. 0.3 or 30%).",
)
@click.option(
    "--by",
    type=click.Choice(STRATEGIES),
    default="pwas",
    show_default=True,
    help="Score to rank by.",
)
@fold_option
@map_refine_options
@click.option(
    "--map-only",
    is_flag=True,
    help="Write only the pruned map, the calibration and the provenance (no earlier "
    "snapshots, poses or stats): the file is as small as the map.",
)
@output_option()
@codec_option(None, " [default: the map's own codec]")
@map_sums_option
@seed_option("Seed of the random strategy and of the refinement's view order.")
@force_option()
@json_option
def prune(
    src: Path,
    keep: float,
    by: str,
    fold: bool,
    refine_iters: int,
    anisotropic: bool,
    seq: Path | None,
    recording: Any,
    device: str,
    map_only: bool,
    dst: Path,
    codec: str | None,
    sums: bool,
    seed: int,
    force: bool,
    as_json: bool,
) -> None:
    """Keep the round(KEEP x N) highest-scoring Gaussians of the map in SRC.

    Only the last /gaussians snapshot (the map) is pruned; poses, calibration, stats and earlier
    snapshots pass through unchanged (with --map-only, only the calibration), and the output
    records where it came from. Rounding is half up; ties are broken by ascending Gaussian id.
    Each Gaussian left out is folded into the nearest kept one (--no-fold: dropped).

    With --refine N the kept Gaussians are refined on the log's keyframes (the sequence given
    by --seq must be the one the log was made from) and on the unpruned map's renders between
    them; the pruned ones never come back, and one whose opacity collapses stays. Each kept
    Gaussian gets three scales and a rotation, to stretch over what it now stands for
    (--isotropic: it keeps one scale).

    \b
    Examples:
      gsc prune run.mcap --keep 0.3 -o run_30.mcap
      gsc prune run.mcap --keep 0.3 --by opacity -o run_30_opacity.mcap
      gsc prune run.mcap --keep 0.3 --no-fold -o run_30_exact.mcap   # the kept ones as they were
      gsc prune run.mcap --keep 0.3 --codec compact -o run_30_compact.mcap
      gsc prune run.mcap --keep 0.3 --refine 500 --seq data/room --map-only -o run_30r.mcap
    """
    check_recording_seq(recording, seq)
    with progress_bar("prune", "step", hidden=as_json) as bar:  # (a fold of a large map: seconds)
        phases = Phases(bar, {"refine": "iter"})
        refine = log_refiner(
            src,
            refine_iters,
            seq,
            device,
            seed,
            phases,
            "prune without --refine",
            anisotropic,
            recording,
        )
        result = prune_log(
            src,
            dst,
            keep,
            by=by,
            seed=seed,
            codec=codec,
            options=CompactOptions(sums=sums),
            refine=refine,
            map_only=map_only,
            fold=fold,
            command=command_line(),
            force=force,
        )
    text = (
        f"kept {result['kept']} of {result['total']} Gaussians (by {by}"
        f"{', the rest folded in' if result['fold'] and result['kept'] < result['total'] else ''}"
        f", {result['codec']})" + refined_text(result)
    )
    emit(result, as_json, f"{text} -> {dst}")
