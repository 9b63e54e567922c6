"""`gsc import-ply`: turn a 3DGS PLY map from any tool into a gscompress log."""

from __future__ import annotations

from pathlib import Path

import click

from gscompress.pipeline import import_ply as run_import

from .options import INPUT_FILE, command_line, emit, force_option, json_option, output_option


@click.command("import-ply", short_help="Make a log of a 3DGS PLY (INRIA or gsplat layout).")
@click.argument("src", type=INPUT_FILE)
@output_option()
@force_option()
@json_option
def import_ply(src: Path, dst: Path, force: bool, as_json: bool) -> None:
    """Make a log holding the 3DGS map in SRC (INRIA or gsplat PLY layout).

    The map has no PWAS scores yet unless SRC carries an `importance` property; score it with
    `gsc score` (needs the sequence) or prune it by opacity.

    \b
    Example:
      gsc import-ply point_cloud.ply -o map.mcap
    """
    result = run_import(src, dst, command=command_line(), force=force)
    emit(result, as_json, f"wrote {dst}: {result['gaussians']} Gaussians")
