"""`gsc prune`: keep the most important fraction of a log's map."""

from __future__ import annotations

from pathlib import Path

import click

from gscompress.io.codec import CompactOptions
from gscompress.ops.select import STRATEGIES
from gscompress.pipeline import prune_log

from .options import (
    INPUT_FILE,
    Ratio,
    codec_option,
    command_line,
    emit,
    force_option,
    json_option,
    output_option,
    seed_option,
    sums_option,
)


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
@output_option()
@codec_option(None, " [default: the map's own codec]")
@sums_option
@seed_option()
@force_option()
@json_option
def prune(
    src: Path,
    keep: float,
    by: str,
    dst: Path,
    codec: str | None,
    sums: bool,
    seed: int,
    force: bool,
    as_json: bool,
) -> None:
    """Keep the round(KEEP x N) highest-scoring Gaussians of the map in SRC.

    Only the last /gaussians snapshot (the map) is pruned; poses, calibration, stats and earlier
    snapshots pass through unchanged, and the output records where it came from. Rounding is half
    up; ties are broken by ascending Gaussian id.

    \b
    Examples:
      gsc prune run.mcap --keep 0.3 -o run_30.mcap
      gsc prune run.mcap --keep 0.3 --by opacity -o run_30_opacity.mcap
      gsc prune run.mcap --keep 0.3 --codec compact -o run_30_compact.mcap
    """
    result = prune_log(
        src,
        dst,
        keep,
        by=by,
        seed=seed,
        codec=codec,
        options=CompactOptions(sums=sums),
        command=command_line(),
        force=force,
    )
    emit(
        result,
        as_json,
        f"kept {result['kept']} of {result['total']} Gaussians (by {by}, {result['codec']}) "
        f"-> {dst}",
    )
