"""Benchmark of a tracking iteration and of its pose update: numpy against torch autograd.

    python bench/tracking.py                  # 160x120, 5000 Gaussians, torch's thread count
    python bench/tracking.py --threads 1 --gaussians 20000

Prints one JSON object per case, in ms per tracking iteration (median and fastest round):
- `pose_numpy`: what `gscompress.slam.tracker.track` does around the render per iteration: the
  pose increment, `pose_gradient` from a given dL/dT and a `PoseAdam` step.
- `pose_autograd`: the same update with the six numbers as torch leaves: the quaternion
  rotation as torch operations (`gscompress.render.projection.rotation_rows`), autograd back
  from dL/dT, torch's Adam and ExponentialLR. This is the tracker's way before e262dbf
  with the rotation built by the renderer's batched code (timed about 13% slower
  than the old tracker's own code). Its row carries `x_vs_numpy`, the ratio of its time to
  `pose_numpy`'s in this call.
- `track_iteration`: a whole `track` call on the scene (render, loss, backward and
  pose update, cpu backend) divided by its iterations; its row carries `pose_autograd_extra`,
  (pose_autograd - pose_numpy) / track_iteration: what the autograd update would add.
- `project_backward_all` / `project_backward_camera`: the C++ projection's backward on the
  scene with every gradient, and with the camera's only (what tracking asks for since
  77b0266); the second row carries `x_vs_all`.
The scene is `bench/render.py`'s random SLAM-like view at 160x120 with `--gaussians` of them,
observed as it renders from the identity pose, where tracking starts. The cases run
interleaved round by round, so that load from other processes affects all alike.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable
from types import ModuleType

import numpy as np
import torch
from render import make_scene  # bench/render.py (this folder is on sys.path when run)

from gscompress.camera import Intrinsics
from gscompress.render import cpu as cpu_backend
from gscompress.render import render
from gscompress.render.projection import rotation_rows
from gscompress.slam.config import preset
from gscompress.slam.params import RenderInputs
from gscompress.slam.poses import PoseAdam, pose_gradient, pose_increment
from gscompress.slam.tracker import track


def _pose_numpy(g_T: np.ndarray, T0: np.ndarray) -> Callable[[], None]:
    adam, state = PoseAdam(np.full(6, 1e-3), 0.99), {"x": np.zeros(6)}

    def run() -> None:
        x = state["x"]
        torch.tensor(pose_increment(x) @ T0, dtype=torch.float32)  # what the render receives
        state["x"] = adam.step(x, pose_gradient(x, T0, g_T))

    return run


def _pose_autograd(g_T: np.ndarray, T0: np.ndarray) -> Callable[[], None]:
    q = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    tau = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([{"params": [q], "lr": 1e-3}, {"params": [tau], "lr": 1e-3}])
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, 0.99)
    T0_t, g_t = torch.from_numpy(T0), torch.from_numpy(g_T).float()
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)

    def run() -> None:
        R = torch.stack(rotation_rows(torch.cat([q.new_ones(1), q])[None]), dim=1)[0]
        delta = torch.cat([torch.cat([R, tau[:, None]], dim=1), bottom])
        T = (delta @ T0_t).float()
        optimizer.zero_grad(set_to_none=True)
        T.backward(g_t)
        optimizer.step()
        scheduler.step()

    return run


def _scene(n: int) -> tuple[RenderInputs, Intrinsics]:
    """`bench/render.py`'s SLAM-like random view at 160x120 (about 25 Gaussians per pixel)."""
    scene = make_scene(160, 120, n)
    keys = ("means", "quats", "scales", "opacities", "colors")
    return RenderInputs(*(scene[k] for k in keys)), scene["intrinsics"]


def _project_backward(ext: ModuleType, n: int, want_params: bool) -> Callable[[], None]:
    """The C++ projection's backward on the scene, with or without the per-Gaussian grads."""
    inputs, i = _scene(n)
    g = torch.Generator().manual_seed(1)
    grads = [torch.randn(n, k, generator=g) for k in (2, 3)] + [torch.randn(n, generator=g)]
    args = (*inputs[:3], torch.eye(4), i.fx, i.fy, i.cx, i.cy, i.width, i.height, 0.1)

    def run() -> None:
        ext.project_backward(*args, *grads, want_params)

    return run


def _track_iteration(n: int) -> tuple[Callable[[], None], int]:
    inputs, intrinsics = _scene(n)
    with torch.no_grad():
        observed = render(*inputs, intrinsics, torch.eye(4), backend="cpu")
    color, depth = observed.color, observed.depth_normalized
    config = preset("cpu").tracking

    def run() -> None:
        track(inputs, color, depth, intrinsics, np.eye(4), config, backend="cpu")

    return run, config.iters


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=5000, help="Gaussians of the scene")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--calls", type=int, default=400, help="pose updates per round")
    opts = parser.parse_args()
    if opts.threads:
        torch.set_num_threads(opts.threads)
    ext = cpu_backend.load_extension()
    if ext is None:
        raise SystemExit("the C++ kernels are not available (no compiler?): nothing to time")
    rng = np.random.default_rng(0)
    g_T, T0 = rng.normal(size=(4, 4)), np.eye(4)
    track_once, iters = _track_iteration(opts.gaussians)
    cases: dict[str, tuple[Callable[[], None], int, int]] = {  # fn, calls per round, per-iteration
        "pose_numpy": (_pose_numpy(g_T, T0), opts.calls, 1),
        "pose_autograd": (_pose_autograd(g_T, T0), opts.calls, 1),
        "track_iteration": (track_once, 3, iters),
        "project_backward_all": (_project_backward(ext, opts.gaussians, True), opts.calls, 1),
        "project_backward_camera": (_project_backward(ext, opts.gaussians, False), opts.calls, 1),
    }
    times: dict[str, list[float]] = {name: [] for name in cases}
    for fn, calls, _ in cases.values():
        for _ in range(max(calls // 10, 1)):
            fn()
    for _ in range(opts.rounds):
        for name, (fn, calls, per) in cases.items():
            start = time.perf_counter()
            for _ in range(calls):
                fn()
            times[name].append((time.perf_counter() - start) / (calls * per) * 1e3)
    median = {name: statistics.median(ms) for name, ms in times.items()}
    for name, ms in times.items():
        row: dict[str, object] = {
            "case": name,
            "threads": torch.get_num_threads(),
            "ms_per_iteration": round(median[name], 4),
            "ms_per_iteration_min": round(min(ms), 4),
            "load_average": round(os.getloadavg()[0], 2),
        }
        if name == "pose_autograd":
            row["x_vs_numpy"] = round(median[name] / median["pose_numpy"], 1)
        if name == "project_backward_camera":
            row["x_vs_all"] = round(median["project_backward_all"] / median[name], 2)
        if name == "track_iteration":
            row["gaussians"] = opts.gaussians
            extra = median["pose_autograd"] - median["pose_numpy"]
            row["pose_autograd_extra"] = round(extra / median[name], 3)
        print(json.dumps(row))


if __name__ == "__main__":
    main()
