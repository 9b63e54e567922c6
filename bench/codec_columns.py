"""What each compact column's code costs a map's picture, one column at a time.

For the map of a log, each variant codes one attribute (colour linear or asinh at 6-8 bits, log
scale at 6-8 bits, opacity at 6-7 bits) with the codec's own quantiser, leaves the rest exact,
and scores the map with `gsc eval`'s scoring at the log's poses. It prints the PSNR change
against the exact map and the column's zstd bytes per Gaussian (docs/codecs.md, "Colours in
asinh codes, scales in 8 bits").

Usage:
    python bench/codec_columns.py runs/s0_agent_a.mcap --seq room --frames 0:24 --every 2
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import zstandard

from gscompress.gaussians import GaussianMap
from gscompress.io import compact as codec
from gscompress.io.mcap_log import LogReader
from gscompress.pipeline import evaluate_log
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.logs import rewrite_map

VARIANTS: dict[str, tuple[str, int, str]] = {
    "colour, linear 8 bits": ("sh_dc", 8, "linear"),
    "colour, linear 7 bits": ("sh_dc", 7, "linear"),
    "colour, asinh 7 bits": ("sh_dc", 7, "asinh-linear"),
    "colour, asinh 6 bits": ("sh_dc", 6, "asinh-linear"),
    "log scale, 6 bits": ("log_scales", 6, "linear"),
    "log scale, 7 bits": ("log_scales", 7, "linear"),
    "log scale, 8 bits": ("log_scales", 8, "linear"),
    "opacity, 6 bits": ("opacity_logits", 6, "sigmoid-linear"),
    "opacity, 7 bits": ("opacity_logits", 7, "sigmoid-linear"),
}
"""Variant -> (the map attribute it codes, bits, its transform: `codec.LINEAR_TRANSFORMS`)."""


def coded(values: np.ndarray, bits: int, transform: str) -> tuple[np.ndarray, int]:
    """`values` through a linear code of `bits` bits in the transform's space, and the code's
    zstd bytes (byte planes, level `codec.ZSTD_LEVEL`, as a compact column stores it)."""
    forward, inverse = codec.LINEAR_TRANSFORMS[transform]
    flat = forward(values.reshape(len(values), -1).astype(np.float64))
    codes, low, high = codec.quantise_linear(flat, bits)
    size = len(zstandard.ZstdCompressor(level=codec.ZSTD_LEVEL).compress(codec._shuffle(codes)))
    back = inverse(codec.dequantise_linear(codes, low, high, bits).astype(np.float64))
    return back.reshape(values.shape).astype(np.float32), size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path, help="a SLAM log (its last map is measured)")
    parser.add_argument("--seq", type=Path, required=True, help="its sequence")
    parser.add_argument("--frames", default=None, help="frames to score (default: the log's)")
    parser.add_argument("--every", type=int, default=2, help="score every N-th frame")
    opts = parser.parse_args()
    with LogReader(opts.log) as reader:
        exact = reader.read_map()
    exact = exact.select(np.argsort(codec.grid_codes(exact)[3], kind="stable"))  # (as stored)

    with tempfile.TemporaryDirectory() as tmp:

        def psnr(gaussians: GaussianMap) -> float:
            out = Path(tmp) / "map.mcap"
            rewrite_map(
                opts.log,
                out,
                {"name": "bench"},
                lambda _: (gaussians, {}),
                codec="fp32",
                force=True,
            )
            scores = evaluate_log(
                out, opts.seq, ImageOptions(frames=opts.frames, every=opts.every, lpips=False)
            )
            return float(scores["psnr"])

        base = psnr(exact)
        print(f"{opts.log}: {len(exact)} Gaussians, exact map {base:.4f} dB")
        print("| column, code | dPSNR | bytes per Gaussian |\n|---|---|---|")
        for name, (attribute, bits, transform) in VARIANTS.items():
            values, size = coded(getattr(exact, attribute), bits, transform)
            change = psnr(replace(exact, **{attribute: values})) - base
            print(f"| {name} | {change:+.3f} | {size / len(exact):.2f} |", flush=True)


if __name__ == "__main__":
    main()
