"""`gsc export-ply`: one snapshot of a log as a 3DGS PLY or SPZ file (numpy + mcap only, never
torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gscompress.io.files import check_output
from gscompress.io.map_files import map_suffix, write_map_file
from gscompress.io.mcap_log import LogReader


def export_ply(
    src: str | Path,
    dst: str | Path,
    *,
    snapshot: int = -1,
    importance: bool = True,
    force: bool = False,
) -> dict[str, Any]:
    """Write one snapshot of a log (default the last, "the map") as a 3DGS PLY file, or as SPZ
    when `dst` ends in `.spz` (without scores or ids: SPZ has no place for them)."""
    check_output(dst, [src], force, map_suffix(dst))
    with LogReader(src) as log_in:
        gaussians = log_in.read_map(snapshot)
        index = snapshot % log_in.snapshot_count  # read_map refused one out of range
    write_map_file(gaussians, dst, importance=importance, inputs=(src,), force=force)
    return {"output": str(dst), "gaussians": len(gaussians), "snapshot": index}
