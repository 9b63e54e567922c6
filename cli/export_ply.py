"""`gsc export-ply`: write a log's map as a 3DGS PLY or SPZ file for external viewers."""

from __future__ import annotations

from pathlib import Path

import click

from gscompress.pipeline import export_ply as run_export

from .options import INPUT_FILE, emit, force_option, json_option, output_option


@click.command("export-ply", short_help="Write a log's map as 3DGS PLY or SPZ for viewers.")
@click.argument("src", type=INPUT_FILE)
@output_option("Output file: .ply (3DGS PLY) or .spz (SPZ).")
@click.option(
    "--snapshot",
    type=int,
    default=-1,
    show_default=True,
    help="Which /gaussians snapshot (0 = first, -1 = last, the map).",
)
@click.option(
    "--no-importance",
    is_flag=True,
    help="Write only the INRIA 3DGS properties (no importance, sums or ids); SPZ never has them.",
)
@force_option()
@json_option
def export_ply(
    src: Path, dst: Path, snapshot: int, no_importance: bool, force: bool, as_json: bool
) -> None:
    """Write the map in SRC as an INRIA-layout binary 3DGS PLY, or as SPZ when the output
    name ends in .spz.

    Opens in SuperSplat, splat-transform and other 3DGS viewers; the extra `importance`
    property of the PLY lets viewers that colour by a property show the PWAS score. SPZ
    (version 4, Niantic's compressed format) is quantised (positions to 1/4096 m, log scales
    to 1/16, opacity and colour to 8 bits) and keeps the PLY's axes, as splat-transform does.

    \b
    Examples:
      gsc export-ply run.mcap -o run.ply
      gsc export-ply run.mcap -o run.spz
    """
    result = run_export(src, dst, snapshot=snapshot, importance=not no_importance, force=force)
    emit(result, as_json, f"wrote {dst}: {result['gaussians']} Gaussians")
