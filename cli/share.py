"""`gsc share`: cut a budgeted top-K share of a map for another agent."""

from __future__ import annotations

from pathlib import Path

import click

from gscompress.ops.select import STRATEGIES
from gscompress.pipeline import share_log

from .options import Ratio, command_line, emit, force_option, json_option, seed_option


@click.command("share")
@click.argument("src", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("dst", type=click.Path(path_type=Path))
@click.option(
    "--budget",
    type=Ratio(),
    default=0.2,
    show_default=True,
    help="Fraction of the map's Gaussians to share, in (0, 1].",
)
@click.option(
    "--strategy",
    type=click.Choice(STRATEGIES),
    default="pwas",
    show_default=True,
    help="What to rank Gaussians by.",
)
@click.option(
    "--ply",
    type=click.Path(path_type=Path),
    default=None,
    help="Also write the share as a 3DGS PLY file.",
)
@seed_option
@force_option
@json_option
def share(
    src: Path,
    dst: Path,
    budget: float,
    strategy: str,
    ply: Path | None,
    seed: int,
    force: bool,
    as_json: bool,
) -> None:
    """Write the top BUDGET share of the map in SRC to DST (a small gscompress log).

    The share holds the selected Gaussians with all their fields, ids and PWAS sums, and records
    its source, strategy, budget and the selected / total counts.

    \b
    Example:
      gsc share --budget 0.2 agent_a.mcap share.mcap --ply share.ply
    """
    result = share_log(
        src, dst, budget, strategy=strategy, seed=seed, ply=ply, command=command_line(), force=force
    )
    extra = f" and {ply}" if ply else ""
    emit(
        result,
        as_json,
        f"shared {result['selected']} of {result['total']} Gaussians ({strategy}) -> {dst}{extra}",
    )
