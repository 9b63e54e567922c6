"""Benchmark our SPZ codec: bytes per Gaussian against splat-transform's SPZ of the same map, and
encode / decode seconds of a large map against a plain copy of its fp32 bytes.

The large map is N Gaussians (default 1,000,000) made of tiled copies of the log's map, each
tile shifted beside the last and jittered (positions by 1 mm, log scales, opacity logits and
colour by 0.01-0.05) so that it does not compress like a repeat. splat-transform (from
tests/js, `make js-deps`) is skipped when node is missing. Torch is never imported.

Usage: python bench/spz.py LOG.mcap [--gaussians 1000000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

import numpy as np

from gscompress.gaussians import GaussianMap
from gscompress.io import spz
from gscompress.io.mcap_log import read_map
from gscompress.io.ply import write_ply

TOOL = (
    Path(__file__).resolve().parents[1]
    / "tests"
    / "js"
    / "node_modules"
    / ".bin"
    / "splat-transform"
)


def tiled(g: GaussianMap, n: int, seed: int = 0) -> GaussianMap:
    """`n` Gaussians: copies of `g` side by side along x, each jittered."""
    rng = np.random.default_rng(seed)
    extent = float(np.ptp(g.means[:, 0])) * 1.05 + 0.01
    tiles = []
    for i in range(-(-n // len(g))):
        tile = GaussianMap(**{f.name: getattr(g, f.name).copy() for f in fields(g)})
        shift = np.array([i * extent, 0, 0], np.float32)
        tile.means += shift + rng.normal(0, 1e-3, tile.means.shape).astype(np.float32)
        tile.log_scales += rng.normal(0, 0.01, tile.log_scales.shape).astype(np.float32)
        tile.opacity_logits += rng.normal(0, 0.05, len(tile)).astype(np.float32)
        tile.sh_dc += rng.normal(0, 0.01, tile.sh_dc.shape).astype(np.float32)
        tile.ids += np.uint32(i * (int(g.ids.max()) + 1))
        tiles.append(tile)
    return GaussianMap.concat(tiles).select(slice(0, n))


def best_of(repeat: int, run: Callable[[], object]) -> float:
    """The shortest of `repeat` runs, in seconds."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    g = read_map(args.log)
    sizes: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for version in (4, 3):
            data = spz.encode_bytes(g, version=version)
            sizes[f"our spz v{version}"] = len(data)
        if shutil.which("node") and TOOL.exists():
            ply = write_ply(g, Path(tmp) / "map.ply", importance=False)
            theirs = Path(tmp) / "theirs.spz"
            subprocess.run(
                [str(TOOL), "-w", str(ply), str(theirs)], check=True, capture_output=True
            )
            sizes["splat-transform spz"] = theirs.stat().st_size
    for name, size in sizes.items():
        row = {"format": name, "gaussians": len(g), "bytes": size}
        print(json.dumps({**row, "bytes_per_gaussian": round(size / len(g), 2)}))
    big = tiled(g, args.gaussians)
    raw = [getattr(big, f.name) for f in fields(big)]
    copy_s = best_of(args.repeat, lambda: [a.copy() for a in raw])
    for version in (4, 3):
        print(json.dumps(measure(big, version, args.repeat, copy_s)))


def measure(big: GaussianMap, version: int, repeat: int, copy_s: float) -> dict[str, object]:
    """Size, best encode and decode seconds of one SPZ version of a map."""
    data = spz.encode_bytes(big, version=version)
    return {
        "format": f"our spz v{version}",
        "gaussians": len(big),
        "bytes_per_gaussian": round(len(data) / len(big), 2),
        "encode_s": round(best_of(repeat, lambda: spz.encode_bytes(big, version=version)), 3),
        "decode_s": round(best_of(repeat, lambda: spz.decode_bytes(data)), 3),
        "fp32_copy_s": round(copy_s, 4),
        "torch_imported": "torch" in sys.modules,
    }


if __name__ == "__main__":
    main()
