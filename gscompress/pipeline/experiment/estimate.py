"""How long an experiment will take, said before it starts: the render passes its plan takes
(each a forward and a backward render of the map at the working size), counted from the
settings, times one such pass timed on the sequence's first frame."""

from __future__ import annotations

import time
from typing import Any

from gscompress.pipeline.experiment.protocol import (
    ExperimentSettings,
    _rescored,
    halves,
    reference_formats,
    same_budget,
)

TIMED_PASSES = 3
"""Render passes timed for the estimate (after one untimed, which loads the kernels)."""


def agent_frame_counts(s: ExperimentSettings, n: int) -> tuple[int, int]:
    """About how many of the `n` frames agents A and B map."""
    if s.split == "halves":
        a, b = halves(n, s.overlap)
        return len(a), len(b)
    return n // 2, n - n // 2


def render_passes(s: ExperimentSettings, base: Any, n: int) -> int:
    """The render passes of the experiment's steps on `n` frames with SLAM config `base`:
    each SLAM run's tracking, mapping and final refinement iterations and its evaluation, each
    merge's refinement and evaluation, each cross-agent scoring's pose refinement."""
    from gscompress.slam.system import final_iterations

    n_a, n_b = agent_frame_counts(s, n)
    per_frame = base.tracking.iters + base.mapping.iters

    def scored(frames: int) -> int:  # (every `every`-th frame)
        return -(-frames // s.every)

    def slam(frames: int) -> int:
        return frames * (per_frame + 1) + final_iterations(base.mapping, frames) + scored(frames)

    merge = s.merge_iters + scored(n_b) if s.mode == "merge" else slam(n_b)
    scoring = (s.refine_poses + 1) * (scored(n_a) + scored(n_b) + scored(n))
    scoring *= s.refine_poses > 0
    extra_budgets = [b for b in s.sweep if not same_budget(b, s.budget)]
    received = len(s.strategies) + 1  # each strategy at the main budget, A's whole map
    received += s.mode == "merge"  # B refined without a share
    sweep = len(extra_budgets) * len(s.strategies) + len(reference_formats(s))
    per_seed = slam(n_a) + slam(n_b) + len(_rescored(s)) * n_a
    per_seed += received * (merge + scoring) + 2 * scoring  # (A and B scored too)
    total = 2 * slam(n) + scoring + s.seeds * per_seed
    return total + s.sweep_seeds * sweep * (merge + scoring)


def seconds_per_pass(sequence: Any, base: Any, device: str = "auto") -> float:
    """Seconds of one forward and backward render of the sequence's first frame, back-projected
    (`gaussians_from_rgbd`: one Gaussian a pixel, as a run's first map), at the working size."""
    import numpy as np
    import torch

    from gscompress.camera import invert_transform
    from gscompress.ops.score import activated_tensors
    from gscompress.render import render, resolve_backend, resolve_device
    from gscompress.slam.densify import gaussians_from_rgbd

    frame = sequence.frame(0)
    T = np.eye(4) if frame.T_world_cam is None else frame.T_world_cam
    gaussians = gaussians_from_rgbd(frame.color, frame.depth, sequence.intrinsics, T)
    torch_device = resolve_device(device, base.backend)
    backend = resolve_backend(base.backend, torch_device)
    tensors = activated_tensors(gaussians, torch_device)
    tensors["means"].requires_grad_(True)
    T_cam_world = torch.as_tensor(invert_transform(T), dtype=torch.float32, device=torch_device)
    times = []
    for _ in range(1 + TIMED_PASSES):
        start = time.perf_counter()
        t = tensors
        out = render(t["means"], t["quats"], t["scales"], t["opacities"], t["colors"],
                     sequence.intrinsics, T_cam_world, backend=backend)  # fmt: skip
        out.color.sum().backward()
        times.append(time.perf_counter() - start)
    return min(times[1:])


def estimate(s: ExperimentSettings, base: Any, sequence: Any, steps: int) -> dict[str, Any]:
    """What `gsc experiment` says before it starts: its steps, render passes and seconds."""
    passes = render_passes(s, base, len(sequence))
    seconds = passes * seconds_per_pass(sequence, base, s.device)
    return {"steps": steps, "render_passes": passes, "seconds": seconds}
