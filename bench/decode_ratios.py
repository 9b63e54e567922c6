"""Measure the decode ratio of legitimate files, per format, as the decode budget counts it.

For each map given (a log's last snapshot, or a map file), writes it in every format gsc reads
(fp32, fp16 and compact logs, SPZ v3 and v4, PLY; compressed PLY and SOG with
`@playcanvas/splat-transform` when it is installed), also promoted to SH degree 3 with zero
higher coefficients (the most compressible legitimate map: every SH stream a run of one code),
and reports what each decodes to over its bytes (`gscompress.io.decode_budget`: `map_bytes`
over the file, or over the compact message), the largest chunk ratio of every log read, and
the pixels over the bytes of every frame of the sequences given. Prints one JSON object per
file and a summary of the largest ratio per format beside the budget's ratio.

Usage: python bench/decode_ratios.py MAP_OR_LOG... [--seq SEQ]... [--out results.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from gscompress.gaussians import SH_REST_COUNTS, GaussianMap
from gscompress.io.compact import CompactGaussians
from gscompress.io.decode_budget import FORMATS, map_bytes
from gscompress.io.map_files import read_map_file
from gscompress.io.mcap_bounds import BoundedStream, file_records
from gscompress.io.mcap_log import TOPIC_GAUSSIANS, LogMetadata, LogReader, LogWriter
from gscompress.io.ply import write_ply
from gscompress.io.sog import splat_transform
from gscompress.io.spz import write_spz


def promoted(gaussians: GaussianMap, degree: int = 3) -> GaussianMap:
    """The map at SH degree `degree`, its higher coefficients zero."""
    k = SH_REST_COUNTS[degree]
    return replace(gaussians, sh_rest=np.zeros((len(gaussians), k, 3), np.float32))


def chunk_ratio(path: Path) -> float:
    """The largest uncompressed / compressed size of a log's chunks."""
    from mcap.records import Chunk

    worst = 0.0
    with open(path, "rb") as f:
        for record in file_records(BoundedStream(f, str(path)), open_chunks=False):
            if isinstance(record, Chunk) and record.data:
                worst = max(worst, record.uncompressed_size / len(record.data))
    return worst


def log_rows(path: Path, label: str) -> list[dict[str, Any]]:
    """The ratios of a log: its map over the file, its compact message over its bytes, its
    chunks."""
    with LogReader(path) as log:
        snapshot = log.read_snapshot()
        messages = list(log.iter_messages([TOPIC_GAUSSIANS]))
    g = snapshot.gaussians
    decoded = map_bytes(len(g), g.sh_degree)
    rows = [
        {"format": "log", "file": label, "ratio": decoded / path.stat().st_size},
        {"format": "mcap-chunk", "file": label, "ratio": chunk_ratio(path)},
    ]
    if snapshot.codec == "compact":
        message = CompactGaussians.FromString(messages[-1][2].data)
        decoded = map_bytes(int(message.count), int(message.sh_degree))
        rows.append(
            {"format": "compact", "file": label, "ratio": decoded / len(messages[-1][2].data)}
        )
    return rows


def map_rows(g: GaussianMap, name: str, folder: Path) -> list[dict[str, Any]]:
    """The ratios of one map in every format."""
    rows: list[dict[str, Any]] = []
    decoded = map_bytes(len(g), g.sh_degree)
    for codec in ("fp32", "fp16", "compact"):
        path = folder / f"{name}.{codec}.mcap"
        with LogWriter(path, LogMetadata()) as log:
            log.write_gaussians(g, 0, codec)
        rows += log_rows(path, path.name)
    for version in (3, 4):
        path = write_spz(g, folder / f"{name}.v{version}.spz", version=version)
        rows.append({"format": "spz", "file": path.name, "ratio": decoded / path.stat().st_size})
    ply = write_ply(g, folder / f"{name}.ply", importance=False)
    rows.append({"format": "ply", "file": ply.name, "ratio": decoded / ply.stat().st_size})
    command = splat_transform()
    if command is not None:
        for suffix, kind in ((".compressed.ply", "compressed-ply"), (".sog", "sog")):
            out = folder / f"{name}{suffix}"
            subprocess.run(
                [command, "-w", "-g", "cpu", str(ply), str(out)], check=True, capture_output=True
            )
            read = read_map_file(out)
            ratio = map_bytes(len(read), read.sh_degree) / out.stat().st_size
            rows.append({"format": kind, "file": out.name, "ratio": ratio})
    return rows


def image_rows(sequence: Path) -> list[dict[str, Any]]:
    """The pixels over the bytes of every image of a sequence folder."""
    rows = []
    for path in sorted(sequence.rglob("*")):
        if path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
            continue
        with Image.open(path) as image:
            bands = len(image.getbands())
            per = 2 if image.mode.startswith("I;16") else 1
            decoded = image.size[0] * image.size[1] * bands * per
        rows.append({"format": "image", "file": str(path), "ratio": decoded / path.stat().st_size})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("maps", nargs="+", type=Path, help="logs or map files")
    parser.add_argument("--seq", action="append", type=Path, default=[], help="a sequence")
    parser.add_argument("--out", type=Path, help="also write the rows as JSON here")
    args = parser.parse_args()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.maps:
            if path.suffix == ".mcap":
                rows += log_rows(path, path.name)
                with LogReader(path) as log:
                    g = log.read_map()
            else:
                g = read_map_file(path)
            rows += map_rows(g, path.stem, Path(tmp))
            if g.sh_degree < 3:
                rows += map_rows(promoted(g), f"{path.stem}.sh3", Path(tmp))
    for sequence in args.seq:
        rows += image_rows(sequence)
    for row in rows:
        row["ratio"] = round(row["ratio"], 2)
        print(json.dumps(row))
    summary = {}
    for name, spec in FORMATS.items():
        found = [r for r in rows if r["format"] == name]
        if found:
            worst = max(found, key=lambda r: r["ratio"])
            summary[name] = {"budget": spec.ratio, "largest": worst["ratio"], "file": worst["file"]}
    print(json.dumps({"summary": summary}, indent=1))
    if args.out:
        args.out.write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
