"""Benchmark the map codecs: bytes, encode / decode speed and the picture each one keeps.

For each map (the synthetic demo map, the final map of every sequence in ../shared/data mapped
with the cpu preset, and an anisotropic map of the synthetic sequence), every format:

- fp32 / fp16: our `/gaussians` foxglove.PointCloud message;
- compact: our own message as a share sends it by default (PWAS sums, no ids), with the ids too
  (`gsc share --ids`; a log's own maps), with the score alone (`--no-sums`), and bare (geometry
  and colour only, what a viewer needs);
- spz, spz-v3: our SPZ file, version 4 (zstd streams) and 3 (gzip);
- st-spz, st-sog, st-cply: `@playcanvas/splat-transform`'s SPZ, SOG and compressed PLY of our
  PLY (where node and tests/js/node_modules are present; `make js-deps`), read back by
  converting each to PLY with the same tool; a SOG's size is its `.sog` file as written;
- ply, ply+zstd: the 3DGS PLY file, and that file zstd-compressed (level 19).

It reports bytes and bytes per Gaussian, and the PSNR / SSIM of each decoded map rendered at
the log's estimated poses (every `--every`-th frame), against the ground-truth frames and
against the fp32 map's own renders, at the working size and at the sequence's full size. Then
encode and decode seconds of 1M Gaussians (tiled copies of the synthetic map, each jittered so
that it does not compress like a repeat) for our codecs, beside a plain copy of the fp32 bytes
in the same run.

SLAM logs are cached in `--out` (a rerun maps nothing it already has).

Usage:
    python bench/codec.py                         # every map: tens of minutes on 2 cores
    python bench/codec.py --maps synthetic --every 8
    python bench/codec.py --speed-only
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import zstandard

from gscompress.gaussians import GaussianMap
from gscompress.io import spz
from gscompress.io.codec import SHARE_DEFAULTS, SHARE_IDS, get_codec
from gscompress.io.compact import COMPACT_DEFAULTS, CompactOptions
from gscompress.io.mcap_log import LogReader, decode_map_message, encode_map
from gscompress.io.ply import read_ply, write_ply
from gscompress.io.sog import splat_transform

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

SEQUENCES = {
    "tabletop": ("tsdffusion_tabletop_box", None),
    "office-frag1": ("3dmatch_office_frag1", None),
    "icl-living1": ("icl_livingroom1_clean_o3d211", "0:120"),
    "replica-office0": ("replica_office0_nvblox4", None),
}
"""Map name -> (folder in ../shared/data, frame subset)."""

COMPACT_VARIANTS = {
    "compact": SHARE_DEFAULTS,
    "compact-ids": CompactOptions(ids=True),
    "compact-score": CompactOptions(ids=SHARE_IDS, sums=False),
    "compact-bare": CompactOptions(ids=False, sums=False, score=False),
}

Codec = tuple[Callable[[GaussianMap], bytes], Callable[[bytes], GaussianMap]]


def our_codecs() -> dict[str, Codec]:
    """Format name -> (encode to bytes, decode bytes), torch-free."""

    def ours(codec: str, options: CompactOptions = COMPACT_DEFAULTS) -> Codec:
        return (
            lambda g: encode_map(g, codec, 0, options).SerializeToString(),
            lambda data: decode_map_message(data, get_codec(codec).schema)[0],
        )

    codecs = {"fp32": ours("fp32"), "fp16": ours("fp16")}
    codecs.update({name: ours("compact", options) for name, options in COMPACT_VARIANTS.items()})
    codecs["spz"] = (spz.encode_bytes, spz.decode_bytes)  # version 4 (zstd streams)
    codecs["spz-v3"] = (partial(spz.encode_bytes, version=3), spz.decode_bytes)  # gzip
    return codecs


def file_formats(g: GaussianMap, tmp: Path) -> dict[str, tuple[int, GaussianMap | None]]:
    """PLY, PLY+zstd and splat-transform's formats: name -> (bytes, decoded map or None)."""
    ply = tmp / "map.ply"
    write_ply(g, ply, force=True)
    data = ply.read_bytes()
    out: dict[str, tuple[int, GaussianMap | None]] = {
        "ply": (len(data), read_ply(ply)),
        "ply+zstd": (len(zstandard.ZstdCompressor(level=19).compress(data)), read_ply(ply)),
    }
    tool = splat_transform()
    if tool is None:
        logging.warning("node or splat-transform missing (make js-deps): its formats left out")
        return out
    for name, suffix in (("st-spz", ".spz"), ("st-sog", ".sog"), ("st-cply", ".compressed.ply")):
        target = tmp / f"map{suffix}"
        back = tmp / f"back_{name}.ply"
        for path in (target, back):
            path.unlink(missing_ok=True)
        run = [tool, "-w"]
        subprocess.run([*run, str(ply), str(target)], check=True, capture_output=True)
        subprocess.run([*run, str(target), str(back)], check=True, capture_output=True)
        out[name] = (target.stat().st_size, _read_clamped(back))
    return out


def _read_clamped(path: Path) -> GaussianMap:
    """A PLY written by another tool, with infinite opacity logits (opacity exactly 0 or 1,
    which splat-transform writes) clamped to finite ones."""
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    vertex = ply["vertex"].data
    opacity = vertex["opacity"]
    opacity[np.isposinf(opacity)] = 20.0
    opacity[np.isneginf(opacity)] = -20.0
    fixed = path.with_name(path.stem + "_finite.ply")
    ply.write(str(fixed))
    return read_ply(fixed)


# ---------------------------------------------------------------------- maps


def ensure_maps(names: list[str], out: Path) -> dict[str, tuple[Path, Path]]:
    """Name -> (SLAM log, sequence folder), mapping what is not cached in `out` yet."""
    from gscompress.datasets.synthetic import write_synthetic_sequence
    from gscompress.pipeline import slam_file
    from gscompress.pipeline.slam_run.options import SlamOptions
    from gscompress.slam.config import resolve_config

    maps: dict[str, tuple[Path, Path]] = {}
    synthetic = out / "synthetic"
    if any(n.startswith("synthetic") for n in names) and not (synthetic / "rgb.txt").exists():
        write_synthetic_sequence(synthetic, frames=40, size=(160, 120), supersample=2, force=True)
    for name in names:
        log = out / f"{name}.mcap"
        if name.startswith("synthetic"):
            seq, frames = synthetic, None
        else:
            folder, frames = SEQUENCES[name]
            seq = DATA / folder
            if not seq.exists():
                logging.warning("%s is not here: %s left out", seq, name)
                continue
        if not log.exists():
            config = resolve_config("cpu")
            if name == "synthetic-aniso":
                config = config.with_overrides(isotropic=False)
            logging.warning("mapping %s (cpu preset) into %s", seq, log)
            slam_file(seq, log, SlamOptions(frames=frames), config=config, command="bench/codec.py")
        maps[name] = (log, seq)
    return maps


# ---------------------------------------------------------------------- quality


def render_set(
    log: Path, seq: Path, every: int, full: bool
) -> tuple[Any, list[Any], list[np.ndarray]]:
    """(intrinsics, frames, camera-to-world poses) of every `every`-th posed frame of the log's
    sequence, at the log's working size or the sequence's full size."""
    from gscompress.datasets import open_sequence
    from gscompress.io.mcap_log import TOPIC_POSE
    from gscompress.pipeline.logs import frames_with_poses, open_log_sequence

    with LogReader(log) as reader:
        meta = reader.metadata
        pose_ns, poses = reader.read_poses(TOPIC_POSE)
    size = None
    if full:
        native = open_sequence(seq, frames=meta.frames or "all").intrinsics
        size = (native.width, native.height)
    sequence = open_log_sequence(seq, log, meta, None, size)
    positions, index = frames_with_poses(sequence, pose_ns, log)
    chosen = range(0, len(positions), every)
    frames = [sequence.frame(int(positions[k])) for k in chosen]
    return sequence.intrinsics, frames, [poses[index[k]] for k in chosen]


def quality(
    g: GaussianMap, views: tuple[Any, list[Any], list[np.ndarray]], reference: list[np.ndarray]
) -> dict[str, float]:
    """Mean PSNR / SSIM of `g`'s renders against the frames (valid depth) and against
    `reference` renders (every pixel)."""
    from gscompress.metrics import psnr, ssim

    renders = render_all(g, views)
    frames = views[1]
    gt = [psnr(r, f.color, f.depth > 0) for r, f in zip(renders, frames, strict=True)]
    gt_ssim = [ssim(r, f.color, f.depth > 0) for r, f in zip(renders, frames, strict=True)]
    ref = [psnr(r, x, np.ones(r.shape[:2], bool)) for r, x in zip(renders, reference, strict=True)]
    return {
        "psnr_gt": float(np.mean(gt)),
        "ssim_gt": float(np.mean(gt_ssim)),
        "psnr_vs_fp32": float(np.mean(ref)),
    }


def render_all(g: GaussianMap, views: tuple[Any, list[Any], list[np.ndarray]]) -> list[np.ndarray]:
    """Colour renders of `g` at each view's pose."""
    from gscompress.ops.evaluate import render_view
    from gscompress.ops.score import activated_tensors

    intrinsics, _, poses = views
    params = activated_tensors(g)
    return [render_view(params, pose, intrinsics)[0] for pose in poses]


# ---------------------------------------------------------------------- speed


def tiled(g: GaussianMap, n: int, seed: int = 0) -> GaussianMap:
    """`n` Gaussians: copies of `g` side by side along x, each jittered (positions by a tenth
    of the median scale, colours and opacities slightly) so they do not compress as repeats."""
    rng = np.random.default_rng(seed)
    copies = -(-n // len(g))
    width = float(np.ptp(g.means[:, 0])) * 1.1 + 1e-3
    parts = []
    for c in range(copies):
        part = g.select(slice(None))
        part.means = part.means + np.array([c * width, 0, 0], np.float32)
        sigma = float(np.median(np.exp(g.log_scales)))
        part.means += rng.normal(0, 0.1 * sigma, part.means.shape).astype(np.float32)
        part.sh_dc += rng.normal(0, 0.01, part.sh_dc.shape).astype(np.float32)
        part.opacity_logits += rng.normal(0, 0.05, part.opacity_logits.shape).astype(np.float32)
        part.ids = part.ids + np.uint32(c * (int(g.ids.max()) + 1))
        parts.append(part)
    return GaussianMap.concat(parts).select(slice(0, n))


def speed(g: GaussianMap, codecs: dict[str, Codec], n: int, repeats: int) -> dict[str, Any]:
    """Encode / decode seconds of `n` tiled Gaussians per codec (best of `repeats`), and a
    plain copy of the fp32 message's bytes as the baseline."""
    big = tiled(g, n)
    fp32 = codecs["fp32"][0](big)
    baseline = min(_timed(bytearray, fp32) for _ in range(repeats))
    out: dict[str, Any] = {"gaussians": n, "copy_fp32_s": baseline, "codecs": {}}
    for name, (encode, decode) in codecs.items():
        data = encode(big)
        enc = min(_timed(encode, big) for _ in range(repeats))
        dec = min(_timed(decode, data) for _ in range(repeats))
        out["codecs"][name] = {
            "encode_s": enc,
            "decode_s": dec,
            "encode_vs_copy": enc / baseline,
            "decode_vs_copy": dec / baseline,
            "bytes_per_gaussian": len(data) / n,
        }
    return out


def _timed(f: Callable[[Any], object], arg: Any) -> float:
    start = time.perf_counter()
    f(arg)
    return time.perf_counter() - start


# ---------------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", default=",".join(["synthetic", *SEQUENCES, "synthetic-aniso"]))
    parser.add_argument("--out", type=Path, default=ROOT / "bench_out" / "codec")
    parser.add_argument("--every", type=int, default=5, help="render every N-th posed frame")
    parser.add_argument("--gaussians", type=int, default=1_000_000, help="for the speed test")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--speed-only", action="store_true")
    parser.add_argument("--no-speed", action="store_true")
    opts = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    opts.out.mkdir(parents=True, exist_ok=True)
    names = ["synthetic"] if opts.speed_only else opts.maps.split(",")
    codecs = our_codecs()
    report: dict[str, Any] = {
        "machine": f"{platform.node()} {platform.processor() or platform.machine()}",
        "python": sys.version.split()[0],
        "commit": _commit(),
        "maps": {},
    }
    result = opts.out / ("codec_speed.json" if opts.speed_only else "codec.json")
    for name in names:  # one map at a time: each table as soon as its map is there
        maps = ensure_maps([name], opts.out)
        if name in maps and not opts.speed_only:
            report["maps"][name] = bench_map(name, *maps[name], codecs, opts.every)
            print(table(report["maps"][name], name), flush=True)
            result.write_text(json.dumps(report, indent=1))
    if not opts.no_speed:
        with LogReader(ensure_maps(["synthetic"], opts.out)["synthetic"][0]) as reader:
            g = reader.read_map()
        report["speed"] = speed(g, codecs, opts.gaussians, opts.repeats)
        print(speed_table(report["speed"]), flush=True)
    result.write_text(json.dumps(report, indent=1))
    print(f"wrote {result}")


def bench_map(
    name: str, log: Path, seq: Path, codecs: dict[str, Codec], every: int
) -> dict[str, Any]:
    """Bytes and picture of every format for one map."""
    with LogReader(log) as reader:
        g = reader.read_map()
    decoded: dict[str, tuple[int, GaussianMap | None]] = {}
    for codec_name, (encode, decode) in codecs.items():
        data = encode(g)
        decoded[codec_name] = (len(data), decode(data))
    with tempfile.TemporaryDirectory() as tmp:
        decoded.update(file_formats(g, Path(tmp)))
    result: dict[str, Any] = {"gaussians": len(g), "isotropic": g.isotropic, "formats": {}}
    for size_name, full in (("working", False), ("full", True)):
        views = render_set(log, seq, every, full)
        intrinsics = views[0]
        result[f"{size_name}_size"] = [intrinsics.width, intrinsics.height]
        reference = render_all(g, views)
        for fmt, (nbytes, back) in decoded.items():
            entry = result["formats"].setdefault(
                fmt, {"bytes": nbytes, "bytes_per_gaussian": nbytes / len(g)}
            )
            if back is not None:
                q = quality(back, views, reference)
                entry.update({f"{k}_{size_name}": v for k, v in q.items()})
    return result


def table(result: dict[str, Any], name: str) -> str:
    """Markdown table of one map's formats."""
    w, f = result["working_size"], result["full_size"]
    lines = [
        f"\n### {name}: {result['gaussians']} Gaussians, "
        f"{'isotropic' if result['isotropic'] else 'anisotropic'}\n",
        f"| format | bytes | B/Gaussian | PSNR GT {w[0]}x{w[1]} | dPSNR | vs fp32 | "
        f"PSNR GT {f[0]}x{f[1]} | dPSNR | vs fp32 | SSIM GT |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    base = result["formats"]["fp32"]
    for fmt, e in result["formats"].items():
        cells = [fmt, str(e["bytes"]), f"{e['bytes_per_gaussian']:.2f}"]
        for size in ("working", "full"):
            p = e.get(f"psnr_gt_{size}")
            if p is None:
                cells += ["", "", ""]
                continue
            cells += [
                f"{p:.3f}",
                f"{p - base[f'psnr_gt_{size}']:+.3f}",
                f"{e[f'psnr_vs_fp32_{size}']:.1f}",
            ]
        s = e.get("ssim_gt_working")
        cells.append("" if s is None else f"{s:.4f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def speed_table(s: dict[str, Any]) -> str:
    """Markdown table of the speed test."""
    lines = [
        f"\n### {s['gaussians']:,} Gaussians: encode / decode seconds "
        f"(plain copy of the fp32 bytes: {s['copy_fp32_s'] * 1000:.1f} ms)\n",
        "| codec | encode s | decode s | encode / copy | decode / copy | B/Gaussian |",
        "|---|---|---|---|---|---|",
    ]
    for name, e in s["codecs"].items():
        lines.append(
            f"| {name} | {e['encode_s']:.3f} | {e['decode_s']:.3f} | {e['encode_vs_copy']:.0f}x "
            f"| {e['decode_vs_copy']:.0f}x | {e['bytes_per_gaussian']:.2f} |"
        )
    return "\n".join(lines)


def _commit() -> str:
    try:
        return subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


if __name__ == "__main__":
    main()
