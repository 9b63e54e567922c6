"""Map files other tools read: 3DGS PLY (plain or PlayCanvas-compressed), SPZ and SOG, by name
and content.

Reading looks at the first bytes: an SPZ file (gzip or an NGSP header) goes to `spz`, a zip (or
a `.sog` or `meta.json` name) to `sog`, a PLY file to `ply` (which recognises the compressed
layout from its header, whatever the file is called); other content is refused by the reader
its name points to. Writing goes by suffix:
`.spz` writes SPZ, anything else a 3DGS PLY.
"""

from __future__ import annotations

import logging
from pathlib import Path

from gscompress.errors import PlyFormatError
from gscompress.gaussians import GaussianMap
from gscompress.io.ply import read_ply, write_ply
from gscompress.io.sog import read_sog
from gscompress.io.spz import is_spz, read_spz, write_spz

log = logging.getLogger(__name__)

MAP_SUFFIXES = (".ply", ".spz")
"""Suffixes of the map files written (and read; `.compressed.ply` is a `.ply`)."""


def read_map_file(path: str | Path) -> GaussianMap:
    """The validated map in a 3DGS PLY, compressed PLY, SPZ or SOG file.

    Raises:
        PlyFormatError, SpzFormatError, SogFormatError: missing or not a readable map.
    """
    path = Path(path)
    if not path.is_file():
        raise PlyFormatError(f"{path}: no such file")
    with open(path, "rb") as f:
        head = f.read(4)
    if is_spz(head) or (path.suffix.lower() == ".spz" and not head.startswith(b"ply")):
        return read_spz(path)
    if path.suffix.lower() == ".sog" or path.name == "meta.json" or head == b"PK\x03\x04":
        return read_sog(path)
    return read_ply(path)


def write_map_file(
    gaussians: GaussianMap,
    path: str | Path,
    *,
    importance: bool = True,
    inputs: tuple[str | Path, ...] = (),
    force: bool = False,
) -> Path:
    """Write a map as SPZ (a `.spz` name) or 3DGS PLY (any other), atomically.

    Args:
        importance: in a PLY, also write the scores, sums and ids (SPZ has no place for them).

    Returns:
        The output path.
    """
    if map_suffix(path) == ".spz":
        if importance and gaussians.has_importance:
            log.debug("SPZ stores no importance scores or ids: %s leaves them out", path)
        return write_spz(gaussians, path, inputs=inputs, force=force)
    return write_ply(gaussians, path, importance=importance, inputs=inputs, force=force)


def map_suffix(path: str | Path) -> str:
    """The kind of map file a name asks for: `.spz` or `.ply`."""
    return ".spz" if Path(path).suffix.lower() == ".spz" else ".ply"
