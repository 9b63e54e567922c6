"""`gsc import-ply`: turn a 3DGS map file from any tool (PLY, compressed PLY, SPZ, SOG) into
a gscompress log."""

from __future__ import annotations

from pathlib import Path

import click

from gscompress.pipeline import import_ply as run_import

from .options import INPUT_FILE, command_line, emit, force_option, json_option, output_option


@click.command(
    "import-ply", short_help="Make a log of a 3DGS map: PLY, compressed PLY, SPZ or SOG."
)
@click.argument("src", type=INPUT_FILE)
@output_option()
@force_option()
@json_option
def import_ply(src: Path, dst: Path, force: bool, as_json: bool) -> None:
    """Make a log holding the 3DGS map in SRC: a PLY (INRIA or gsplat layout), a PlayCanvas /
    SuperSplat compressed PLY (recognised by its header, whatever its name), an SPZ file
    (versions 2-4, recognised by its content) or a PlayCanvas SOG (version 2: a .sog bundle
    or its meta.json).

    The map has no PWAS scores yet unless SRC carries an `importance` property; score it with
    `gsc score` (needs the sequence) or prune it by opacity. SPZ, SOG and compressed PLY hold no ids
    (the Gaussians are numbered 0..N-1) and are quantised (SPZ: positions to 1/4096 m, log
    scales to 1/16, opacity and colour to 8 bits).

    \b
    Examples:
      gsc import-ply point_cloud.ply -o map.mcap
      gsc import-ply scene.compressed.ply -o map.mcap
      gsc import-ply scene.spz -o map.mcap
      gsc import-ply scene.sog -o map.mcap
    """
    result = run_import(src, dst, command=command_line(), force=force)
    emit(result, as_json, f"wrote {dst}: {result['gaussians']} Gaussians")
