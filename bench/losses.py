"""Benchmark of the SLAM losses with their backward: the cpu backend's kernels against pure torch.

    python bench/losses.py                    # 160x120, torch's default thread count
    python bench/losses.py --threads 1 --size 320x240

Prints one JSON object per loss and backend. The mapping loss (paper Eq. 2-3: L1, SSIM, depth,
illumination) takes its mean SSIM from the fused C++ kernel when the render came from the cpu
backend and from `gscompress.metrics.ssim_maps` otherwise; the tracking loss (Eq. 4-5) is the
same torch code for both and is timed once. `speedup_vs_torch` is the ratio of the pure-torch
mapping loss's time to the kernel's, both measured in this call, interleaved round by round so
that load from other processes affects both alike.

Inputs are random images of the given size with a tenth of the depth missing, a render that
differs from the observation, and (for tracking) a silhouette of which about 80% passes the
mask. Each round times `--iters` calls after warm-up; the figures are the median and the fastest
round, in ms per call (forward + backward, new leaf tensors every call as in a SLAM step).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable

import torch

from gscompress.render import RenderOutput
from gscompress.render import cpu as cpu_backend
from gscompress.slam.config import preset
from gscompress.slam.losses import depth_edges, mapping_loss, tracking_loss


def _inputs(width: int, height: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    depth_gt = torch.rand(height, width, generator=g) + 1.0
    depth_gt[: height // 10] = 0.0
    return {
        "color_gt": torch.rand(height, width, 3, generator=g),
        "depth_gt": depth_gt,
        "color": torch.rand(height, width, 3, generator=g),
        "depth": depth_gt + 0.02 * torch.randn(height, width, generator=g),
        "silhouette": (0.95 + 0.06 * torch.rand(height, width, generator=g)).clamp(max=1.0),
    }


def _step(kind: str, backend: str, x: dict[str, torch.Tensor]) -> Callable[[], None]:
    """One loss evaluation with its backward, on fresh leaves."""
    config = preset("cpu")
    no_radii = torch.zeros(0, dtype=torch.int32)
    edges = depth_edges(x["depth_gt"], config.mapping.illum_edge_sigma)

    def run() -> None:
        color = x["color"].clone().requires_grad_(True)
        depth = x["depth"].clone().requires_grad_(True)
        out = RenderOutput(color, depth, depth, x["silhouette"], None, backend, lambda: no_radii)
        if kind == "mapping":
            terms = mapping_loss(out, x["color_gt"], x["depth_gt"], config.mapping, edges)
        else:
            terms = tracking_loss(out, x["color_gt"], x["depth_gt"], config.tracking)
        terms.total.backward()

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="160x120", help="WxH")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--iters", type=int, default=200, help="calls per round")
    parser.add_argument("--rounds", type=int, default=5)
    opts = parser.parse_args()
    if opts.threads:
        torch.set_num_threads(opts.threads)
    if cpu_backend.load_extension() is None:
        raise SystemExit("the C++ kernels are not available (no compiler?): nothing to compare")
    width, height = (int(v) for v in opts.size.lower().split("x"))
    x = _inputs(width, height)
    cases = {
        ("mapping", "cpu"): _step("mapping", "cpu", x),
        ("mapping", "torch"): _step("mapping", "torch", x),
        ("tracking", "torch"): _step("tracking", "torch", x),
    }
    times: dict[tuple[str, str], list[float]] = {key: [] for key in cases}
    for fn in cases.values():
        for _ in range(max(opts.iters // 10, 3)):
            fn()
    for _ in range(opts.rounds):
        for key, fn in cases.items():
            start = time.perf_counter()
            for _ in range(opts.iters):
                fn()
            times[key].append((time.perf_counter() - start) / opts.iters * 1e3)
    torch_map = statistics.median(times[("mapping", "torch")])
    for (kind, backend), ms in times.items():
        row = {
            "loss": kind,
            "backend": backend,
            "size": [width, height],
            "threads": torch.get_num_threads(),
            "ms_forward_backward": round(statistics.median(ms), 3),
            "ms_forward_backward_min": round(min(ms), 3),
            "load_average": round(os.getloadavg()[0], 2),
        }
        if (kind, backend) == ("mapping", "cpu"):
            row["speedup_vs_torch"] = round(torch_map / statistics.median(ms), 2)
        print(json.dumps(row))


if __name__ == "__main__":
    main()
