"""Benchmark of `gscompress.render.render`: each backend against pure torch, same scenes.

Prints one JSON object per case and backend on stdout:

    python bench/render.py                  # C++ (cpu) and pure torch on the CPU
    python bench/render.py --device cuda    # gsplat and pure torch on the GPU
    python bench/render.py --quick          # 320x240/50k only
    python bench/render.py --march native,x86-64-v3   # the C++ kernels built for two targets

Cases: 160x120/10k, 320x240/50k, 640x480/200k Gaussians. `speedup_vs_torch` is the ratio of
pure torch's forward+backward time to the backend's, both measured in the same call on the same
device. `--march A,B` runs the C++ backend once per `$GSCOMPRESS_MARCH` target (see
`gscompress.render.cpu`), each record naming its `march`; `speedup_vs_march_A` (fwd+bwd) and
`forward_speedup_vs_march_A` compare each with the first target's run of the same case.

Scenes look like a SLAM map seen by its camera: float32 Gaussians spread uniformly over the
view at 2-5 m depth, mildly anisotropic and randomly rotated, with opacities in [0.3, 0.95].
Their size is calibrated so that on average ~25 Gaussians overlap each pixel (counting, for
each Gaussian, the ellipse where its alpha reaches 1/255; `mean_depth_complexity` reports the
value measured on the final scene).

Timings: median over `--iters` iterations (a third of them for pure torch) after 2 warm-up
ones, with `torch.get_num_threads()` threads. `ms_forward` is `render()` with inputs that
require grad (the forward of a training step); `ms_forward_contribution` is the same with
`want_contribution=True`, timed interleaved with it so that load from other processes affects
both alike; `ms_forward_backward` adds the backward of a loss over colour, depth and silhouette;
the `*_min` fields are the fastest iteration of each.
The machine's load average is recorded with each case: figures taken while other processes
compete for the cores are not comparable. On CUDA every timed call ends with
`torch.cuda.synchronize()`, so the times are the GPU's work, not just its launch.

Memory: every case and backend runs in a fresh subprocess; `peak_rss_mb` is that process's
`resource.getrusage(RUSAGE_SELF).ru_maxrss` at the end (whole process: Python, torch, scene,
render), and `baseline_rss_mb` the same figure just before the first render, so the renderer's
own peak is roughly the difference. On CUDA `peak_cuda_mb` is `torch.cuda.max_memory_allocated`
over the timed iterations, scene included.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time
from typing import Any

import torch

from gscompress.camera import Intrinsics
from gscompress.render import render
from gscompress.render.cpu import MARCH_ENV
from gscompress.render.projection import bin_tiles, project_gaussians

CASES = [(160, 120, 10_000), (320, 240, 50_000), (640, 480, 200_000)]
QUICK = [(320, 240, 50_000)]
BACKENDS = {"cpu": ("cpu", "torch"), "cuda": ("gsplat", "torch")}
TARGET_OVERLAP = 25.0
TORCH_MAX_GAUSSIANS = 50_000
"""Largest case the pure-torch backend runs on unless --torch-all: at 640x480 / 200k it was
measured at about 20 s per forward+backward and 12.5 GB peak RSS on the 2-core machine. On
CUDA it runs every case."""


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def make_scene(width: int, height: int, n: int, seed: int = 0) -> dict[str, Any]:
    """A random SLAM-like view with ~TARGET_OVERLAP Gaussians per pixel (float32)."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width
    intr = Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height)
    z = 2.0 + 3.0 * torch.rand(n, generator=g)
    u = (torch.rand(n, generator=g) * 1.04 - 0.02) * width
    v = (torch.rand(n, generator=g) * 1.04 - 0.02) * height
    means = torch.stack([(u - intr.cx) * z / f, (v - intr.cy) * z / f, z], dim=1)
    shape = torch.exp(0.25 * torch.randn(n, 3, generator=g))  # mild anisotropy
    scene: dict[str, Any] = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "unit_scales": shape * (z / f)[:, None],  # 1 px standard deviation at the centre
        "opacities": 0.3 + 0.65 * torch.rand(n, generator=g),
        "colors": torch.rand(n, 3, generator=g),
        "T_cam_world": torch.eye(4),
        "intrinsics": intr,
    }
    sigma_px = 1.0
    for _ in range(6):  # the 0.3 px^2 dilation makes overlap non-linear in the scale
        scene["scales"] = scene["unit_scales"] * sigma_px
        overlap = depth_complexity(scene)
        sigma_px *= math.sqrt(TARGET_OVERLAP / overlap)
    scene["scales"] = scene["unit_scales"] * sigma_px
    return scene


def depth_complexity(scene: dict[str, Any]) -> float:
    """Mean over pixels of the number of Gaussians whose alpha reaches 1/255 there.

    Each visible Gaussian covers the ellipse d^T conic d <= 2 ln(255 o), of area
    pi * 2 ln(255 o) / sqrt(det conic); the sum is divided by the pixel count.
    """
    intr = scene["intrinsics"]
    with torch.no_grad():
        proj = project_gaussians(
            scene["means"], scene["quats"], scene["scales"], scene["T_cam_world"], intr, 0.01
        )
        a, b, c = proj.conics.double().unbind(-1)
        o = scene["opacities"].double()
        area = math.pi * 2 * torch.log(255 * o).clamp(min=0) / torch.sqrt(a * c - b * b)
        area = torch.where(proj.radii > 0, area, torch.zeros_like(area))
    return float(area.sum()) / (intr.width * intr.height)


def timed(*fns, iters: int, sync=lambda: None) -> list[tuple[float, float]]:
    """(median, min) milliseconds of each function, calls interleaved so drift hits all alike.

    `sync` runs after each call and inside its time (CUDA: wait for the queued kernels)."""
    for fn in fns * 2:
        fn()
    sync()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(iters):
        for fn, bucket in zip(fns, times, strict=True):
            t0 = time.perf_counter()
            fn()
            sync()
            bucket.append(time.perf_counter() - t0)
    return [(1000.0 * statistics.median(b), 1000.0 * min(b)) for b in times]


def worker(
    width: int, height: int, n: int, backend: str, iters: int, device: str
) -> dict[str, Any]:
    """Run one case with one backend on `device` in this process and return its JSON record."""
    scene = make_scene(width, height, n)
    intr = scene["intrinsics"]
    cuda = device == "cuda"
    sync = torch.cuda.synchronize if cuda else lambda: None
    if backend == "cpu":
        from gscompress.render.cpu import load_extension

        if load_extension() is None:
            return {"backend": backend, "skipped": "the C++ extension could not be built"}
    params = {
        k: scene[k].to(device).requires_grad_(True)
        for k in ("means", "quats", "scales", "opacities", "colors", "T_cam_world")
    }
    baseline = rss_mb()

    def forward(contribution: bool = False):
        return render(
            params["means"],
            params["quats"],
            params["scales"],
            params["opacities"],
            params["colors"],
            intr,
            params["T_cam_world"],
            backend=backend,
            want_contribution=contribution,
        )

    def forward_backward():
        out = forward()
        loss = out.color.sum() + 0.1 * out.depth.sum() + out.silhouette.sum()
        loss.backward()

    out = forward()
    assert out.backend == backend, out.backend
    with torch.no_grad():
        proj = project_gaussians(
            scene["means"], scene["quats"], scene["scales"], scene["T_cam_world"], intr, 0.01
        )
        intersections = len(bin_tiles(proj, width, height).ids)
    record = {
        "backend": backend,
        "device": torch.cuda.get_device_name() if cuda else "cpu",
        "width": width,
        "height": height,
        "gaussians": n,
        "threads": torch.get_num_threads(),
        "dtype": "float32",
        "mean_depth_complexity": round(depth_complexity(scene), 2),
        "visible": int(out.visible.sum()),
        "tile_intersections": intersections,
        "mean_silhouette": round(float(out.silhouette.mean()), 4),
        "iters": iters,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    fwd, fwd_contribution = timed(forward, lambda: forward(True), iters=iters, sync=sync)
    (fwd_bwd,) = timed(forward_backward, iters=iters, sync=sync)
    record["ms_forward"] = round(fwd[0], 2)
    record["ms_forward_contribution"] = round(fwd_contribution[0], 2)
    record["ms_forward_backward"] = round(fwd_bwd[0], 2)
    record["contribution_overhead_pct"] = round(100.0 * (fwd_contribution[0] / fwd[0] - 1.0), 1)
    # Minima are the figures least disturbed by other processes on a shared machine.
    record["ms_forward_min"] = round(fwd[1], 2)
    record["ms_forward_contribution_min"] = round(fwd_contribution[1], 2)
    record["ms_forward_backward_min"] = round(fwd_bwd[1], 2)
    record["peak_rss_mb"] = round(rss_mb(), 1)
    record["baseline_rss_mb"] = round(baseline, 1)
    if cuda:
        record["peak_cuda_mb"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    return record


def runs_label(backend: str, march: str | None) -> str:
    """The key of one run's record: the backend, and the build target when --march names one."""
    return f"{backend}@{march}" if march else backend


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only 320x240 with 50k Gaussians")
    parser.add_argument("--iters", type=int, default=10, help="timed iterations per figure")
    parser.add_argument(
        "--torch-all", action="store_true", help="also run pure torch on the largest case"
    )
    parser.add_argument(
        "--device",
        choices=sorted(BACKENDS),
        default="cpu",
        help="cpu: C++ and pure torch; cuda: gsplat and pure torch on the GPU",
    )
    parser.add_argument("--backends", help="comma-separated (default: the device's pair)")
    parser.add_argument(
        "--march",
        help="comma-separated $GSCOMPRESS_MARCH targets to build and time the C++ backend for "
        "(e.g. native,x86-64-v3; default: the usual build only)",
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        w, h, n, backend = args.worker.split(",")
        print(json.dumps(worker(int(w), int(h), int(n), backend, args.iters, args.device)))
        return
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: torch sees no CUDA device")
    backends = args.backends.split(",") if args.backends else BACKENDS[args.device]
    marches = args.march.split(",") if args.march else []
    # (label, backend, march): the C++ backend once per target when --march is given.
    runs = [
        (runs_label(b, m), b, m)
        for b in backends
        for m in (marches if b == "cpu" and marches else [None])
    ]
    for width, height, n in QUICK if args.quick else CASES:
        records: dict[str, dict[str, Any]] = {}
        for label, backend, march in runs:
            too_big = args.device == "cpu" and n > TORCH_MAX_GAUSSIANS and not args.torch_all
            if backend == "torch" and too_big:
                records[label] = {
                    "skipped": "too slow and too big for a routine run (about 20 s per "
                    "iteration and 12.5 GB peak RSS when measured); --torch-all runs it"
                }
            else:
                # Pure torch is 10-100x slower: fewer iterations keep the run short.
                slow = backend == "torch" and args.device == "cpu"
                iters = max(3, args.iters // 3) if slow else args.iters
                env = dict(os.environ, **({MARCH_ENV: march} if march else {}))
                proc = subprocess.run(
                    [
                        sys.executable,
                        __file__,
                        "--worker",
                        f"{width},{height},{n},{backend}",
                        "--iters",
                        str(iters),
                        "--device",
                        args.device,
                    ],
                    capture_output=True,
                    text=True,
                    check=False,
                    env=env,
                )
                if proc.returncode != 0:
                    tail = proc.stderr.strip().splitlines()[-1:] or ["no output"]
                    records[label] = {"skipped": f"worker failed: {tail[0]}"}
                else:
                    records[label] = json.loads(proc.stdout.strip().splitlines()[-1])
                if march:
                    records[label]["march"] = march
        # (key, baseline record, timing): each ratio is the baseline's time over the run's.
        ratios = [("speedup_vs_torch", records.get("torch", {}), "ms_forward_backward")]
        if marches:
            first = records.get(runs_label("cpu", marches[0]), {})
            ratios += [
                (f"speedup_vs_march_{marches[0]}", first, "ms_forward_backward"),
                (f"forward_speedup_vs_march_{marches[0]}", first, "ms_forward"),
            ]
        for (_, backend, march), rec in zip(runs, records.values(), strict=True):
            rec = {"backend": backend, "width": width, "height": height, "gaussians": n, **rec}
            for key, ref, field in ratios if march else ratios[:1]:
                if field in ref and field in rec:
                    rec[key] = round(ref[field] / rec[field], 2)
            print(json.dumps(rec), flush=True)


if __name__ == "__main__":
    main()
