"""`gsc import-ply`: a map file of any 3DGS tool (PLY, compressed PLY or SPZ) as a
one-snapshot gscompress log (numpy + mcap only, never torch).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gscompress.io.files import check_output
from gscompress.io.map_files import read_map_file
from gscompress.io.mcap_log import LogMetadata
from gscompress.pipeline.logs import map_log


def import_ply(
    src: str | Path, dst: str | Path, *, command: str = "", force: bool = False
) -> dict[str, Any]:
    """Turn a map file of any 3DGS tool (PLY, compressed PLY or SPZ) into a one-snapshot
    gscompress log."""
    check_output(dst, [src], force, ".mcap")
    gaussians = read_map_file(src)
    meta = LogMetadata().derive({"name": "import-ply"}, src, command)
    return map_log(gaussians, dst, meta, src, force=force)
