"""A log's whole map as it would cross the link in a reference format (`format_share`): the
points of the field on the experiment's rate-distortion plots."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gscompress.errors import InputError
from gscompress.io.codec import DEFAULT_CODEC
from gscompress.io.files import check_output
from gscompress.io.map_files import read_map_file
from gscompress.io.mcap_log import LogReader
from gscompress.pipeline.logs import map_log, recorded_topics
from gscompress.pipeline.share import share_log
from gscompress.pipeline.share.options import ShareOptions

REFERENCE_FORMATS = (DEFAULT_CODEC, "spz", "sog")
"""The formats `format_share` sends a whole map in: the points of the field on a
rate-distortion plot."""


def format_share(
    src: str | Path, dst: str | Path, fmt: str, *, command: str = "", force: bool = False
) -> dict[str, Any]:
    """A log's whole map as it would cross the link in `fmt`, as a share log the receiver merges
    like any other, with the `selected` Gaussians and the bytes that crossed (`file_bytes`).

    "fp32": `share_log` of every Gaussian in the fp32 codec, not folded (`bytes` its map
    message, `file_bytes` the share file). "spz" (our writer, SPZ version 4) and "sog" (written
    by splat-transform, `gscompress.io.sog.write_sog`): the file in that format (`bytes` and
    `file_bytes` its size), read back as `gsc import-ply` reads it. Neither keeps ids or PWAS
    sums: the ids are 0..N-1 and the evidence a merge weighs (alpha x T sums) is zero.

    Raises:
        InputError: an unknown format. MissingDependencyError: "sog" without splat-transform.
    """
    if fmt not in REFERENCE_FORMATS:
        raise InputError(f"unknown format {fmt!r}; choose from {', '.join(REFERENCE_FORMATS)}")
    if fmt == DEFAULT_CODEC:
        got = share_log(
            src, dst, "1", ShareOptions(codec=fmt, fold=False), command=command, force=force
        )
        return {**got, "format": fmt}
    import tempfile

    from gscompress.io.sog import write_sog
    from gscompress.io.spz import write_spz

    check_output(dst, [src], force, ".mcap")
    with LogReader(src) as log_in:
        whole, parent = log_in.read_map(), log_in.metadata
    with tempfile.TemporaryDirectory() as tmp:
        file = Path(tmp) / f"map.{fmt}"
        if fmt == "spz":
            write_spz(whole, file)
        else:
            write_sog(whole, file)
        size = file.stat().st_size
        back = read_map_file(file)
    results = {"format": fmt, "selected": len(back), "bytes": size, "file_bytes": size}
    results |= recorded_topics(parent)
    # (the map is in the sender's world frame, which the log records as a share's does)
    meta = parent.derive({"name": "format-share", "format": fmt}, src, command)
    meta.config = {}  # (as a share's)
    return map_log(back, dst, meta, src, results, force=force)
