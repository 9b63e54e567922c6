"""Is tracking against a Gaussian map biased along the camera's motion? Probes on a sequence
with exact ground truth (the synthetic room), the map always made at the TRUE poses.

Modes:
- `loop`: the run maps every frame at its true pose (`tracking.use_ground_truth`); frame t is
  also tracked (from the constant-velocity guess of the true poses) against the map as it
  stands before frame t is mapped, after it is mapped, and after frame t+1 is mapped.
- `single`: a map made from one frame j alone (the first-frame mapping), and frame t tracked
  against it, for j = t - gap (a view behind) and j = t + gap (a view ahead).
- `dense`: frame t aligned to frame j = t -/+ gap directly (no map): the pixels of t with their
  observed depth warped into j, j's colour and depth sampled bilinearly (dense RGB-D
  odometry), with the tracker's iterations and learning rates.
- `centres`: the run maps every frame at its true pose; after the first and after the last frame
  the Gaussians' centres are compared with the observed depth of that frame (centre depth minus
  the depth measured at its pixel, for centres within 10 cm of it; positive = behind the
  surface), and the first frame's raw back-projection (no mapping iteration) is rendered at its
  own pose (normalised depth minus observed, on flat pixels and at depth discontinuities).

- `pull`: the run maps every frame at its true pose; frame t is rendered from the map of the
  frames before it at `PULL_OFFSETS` along its step (the camera moved back by a fraction of the
  step t-1 -> t) and the L1 error of colour and of depth is summed over the frames, on the
  tracking mask of the true pose, for every pixel and by pixel class: at a depth step, flat and
  textured (the top quarter of the render's change over the offsets), flat and plain. Where each
  curve is lowest (a parabola through its lowest samples; positive = behind the camera) is how
  far back that channel and those pixels would pull tracking.

Variants of `loop` (each leaves pixels out of tracking by zeroing their observed depth, which the
tracking mask requires): `--edges REL` leaves out pixels with a relative depth step above REL to
a 4-neighbour (dilated by a pixel); `--margin M` keeps only pixels whose surface point lies at
least M pixels inside frame t-1's image (away from the map's frontier); `--consolidate N` runs N
mapping iterations over the keyframes before each frame is tracked.

For each tracked frame the error of the estimate is projected on the true step t-1 -> t
("along": a fraction of that step; negative = behind the camera) and on the direction to the
map's view ("towards": a fraction of the t -> j distance). Prints one JSON object.

    python bench/track_bias.py SEQ --mode loop --frames 0:24
    python bench/track_bias.py SEQ --mode single --gap 5
    python bench/track_bias.py SEQ --mode pull
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from gscompress.camera import Intrinsics, invert_transform, transform_points
from gscompress.datasets import open_sequence
from gscompress.datasets.base import Frame, iter_frames
from gscompress.render import render
from gscompress.slam.config import SlamConfig, load_config, preset
from gscompress.slam.keyframes import frame_tensors
from gscompress.slam.losses import tracking_mask
from gscompress.slam.params import RenderInputs, decay_per_step
from gscompress.slam.poses import PoseAdam, orthonormalize, pose_gradient, pose_increment
from gscompress.slam.system import SlamSystem
from gscompress.slam.tracker import constant_velocity, track

PULL_OFFSETS = (-0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3)
"""`pull`: where along frame t's step the map is rendered (fractions of the step, back from the
true pose)."""


def along(est: np.ndarray, truth: np.ndarray, previous: np.ndarray) -> float:
    """The error of `est` along the true step previous -> truth, as a fraction of the step."""
    step = truth[:3, 3] - previous[:3, 3]
    return float((est[:3, 3] - truth[:3, 3]) @ step / (step @ step))


def towards(est: np.ndarray, truth: np.ndarray, reference: np.ndarray) -> float:
    """The error of `est` towards `reference`'s camera, as a fraction of that distance."""
    d = reference[:3, 3] - truth[:3, 3]
    return float((est[:3, 3] - truth[:3, 3]) @ d / (d @ d))


def tracked(
    system: SlamSystem, frame: Frame, guess: np.ndarray, keep: torch.Tensor | None = None
) -> np.ndarray:
    """`frame` tracked against the system's map from `guess` (on the pixels `keep` only)."""
    color, depth = frame_tensors(frame, system.device)
    if keep is not None:
        depth = torch.where(keep, depth, 0.0)
    inputs = system.mapper.params.render_inputs()
    config = system.config
    return track(inputs, color, depth, system.intrinsics, guess, config.tracking).T_world_cam


def summary(values: list[float]) -> dict[str, float]:
    return {"mean": float(np.mean(values)), "median": float(np.median(values))}


def depth_steps(depth: np.ndarray, relative: float) -> torch.Tensor:
    """[H, W] bool: pixels with a relative depth step above `relative` to a 4-neighbour, dilated
    by one pixel."""
    d = torch.as_tensor(depth, dtype=torch.float32)
    pad = F.pad(d[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    step = torch.zeros_like(d)
    for n in (pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]):
        step = torch.maximum(step, torch.where(n > 0, (n - d).abs(), 0.0))
    edge = (step > relative * d).float()[None, None]
    return F.max_pool2d(edge, 3, 1, 1)[0, 0] > 0


def inside(frame: Frame, T_world_other: np.ndarray, K: Intrinsics, margin: float) -> torch.Tensor:
    """[H, W] bool: pixels of `frame` whose surface point (observed depth, true pose) projects at
    least `margin` pixels inside the image of a camera at `T_world_other`."""
    H, W = frame.depth.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d = frame.depth.astype(np.float64)
    points = np.stack([(u - K.cx) / K.fx * d, (v - K.cy) / K.fy * d, d, np.ones_like(d)], -1)
    assert frame.T_world_cam is not None
    q = points @ (invert_transform(T_world_other) @ frame.T_world_cam).T
    z = np.maximum(q[..., 2], 1e-6)
    uu, vv = K.fx * q[..., 0] / z + K.cx, K.fy * q[..., 1] / z + K.cy
    ok = (uu >= margin) & (uu <= W - 1 - margin) & (vv >= margin) & (vv <= H - 1 - margin)
    return torch.as_tensor(ok & (d > 0))


def loop(
    config: SlamConfig,
    frames: list[Frame],
    intrinsics: Intrinsics,
    variant: dict[str, float] | None = None,
) -> dict[str, Any]:
    """The `loop` mode (and its variants: `edges`, `margin`, `consolidate`)."""
    variant = variant or {}
    config = config.with_overrides(**{"tracking.use_ground_truth": True, "prune.stages": ()})
    system = SlamSystem(config, intrinsics, total_frames=None)
    truth = [np.asarray(f.T_world_cam) for f in frames]
    rows: dict[str, list[float]] = {"before": [], "after": [], "after_next": []}
    rng = np.random.default_rng(0)

    def error(t: int) -> float:
        guess = constant_velocity(truth[t - 1], truth[t - 2])
        keep = torch.ones(frames[t].depth.shape, dtype=torch.bool)
        if variant.get("edges"):
            keep &= ~depth_steps(frames[t].depth, variant["edges"])
        if variant.get("margin"):
            keep &= inside(frames[t], truth[t - 1], intrinsics, variant["margin"])
        return along(tracked(system, frames[t], guess, keep), truth[t], truth[t - 1])

    for t, frame in enumerate(frames):
        if t >= 2:
            if variant.get("consolidate"):
                system.mapper.refine(list(system.keyframes), int(variant["consolidate"]), rng)
            rows["before"].append(error(t))
        system.process(frame)
        if t >= 2:
            rows["after"].append(error(t))
        if t >= 3:
            rows["after_next"].append(error(t - 1))
    return {k: {**summary(v), "per_frame": [round(x, 4) for x in v]} for k, v in rows.items()}


def dense_align(
    frame: Frame, reference: Frame, intrinsics: Intrinsics, guess: np.ndarray, config: Any
) -> np.ndarray:
    """`frame`'s pose from dense RGB-D alignment to `reference` (at its true pose)."""
    K, (H, W) = intrinsics, frame.depth.shape
    v, u = torch.meshgrid(torch.arange(H * 1.0), torch.arange(W * 1.0), indexing="ij")
    depth = torch.as_tensor(frame.depth, dtype=torch.float32)
    color = torch.as_tensor(frame.color, dtype=torch.float32)
    points = torch.stack([(u - K.cx) / K.fx * depth, (v - K.cy) / K.fy * depth, depth], -1)
    ref_color = torch.as_tensor(reference.color, dtype=torch.float32).permute(2, 0, 1)[None]
    ref_depth = torch.as_tensor(reference.depth, dtype=torch.float32)[None, None]
    assert reference.T_world_cam is not None
    T_ref = torch.as_tensor(invert_transform(reference.T_world_cam), dtype=torch.float32)
    start = invert_transform(guess)
    x = np.zeros(6)
    rates = np.repeat([config.lr_rotation, config.lr_translation], 3)
    adam = PoseAdam(rates, decay_per_step(config.lr_final_fraction, config.iters))
    for _ in range(config.iters):
        T = torch.tensor(pose_increment(x) @ start, dtype=torch.float32, requires_grad=True)
        rel = T_ref @ torch.linalg.inv(T)
        p = points @ rel[:3, :3].T + rel[:3, 3]
        z = p[..., 2].clamp_min(1e-3)
        grid = torch.stack(
            [
                2 * (K.fx * p[..., 0] / z + K.cx) / (W - 1) - 1,
                2 * (K.fy * p[..., 1] / z + K.cy) / (H - 1) - 1,
            ],
            -1,
        )[None]
        sample: Callable[..., torch.Tensor] = F.grid_sample
        c = sample(ref_color, grid, align_corners=True)[0].permute(1, 2, 0)
        d = sample(ref_depth, grid, align_corners=True)[0, 0]
        dn = sample(ref_depth, grid, align_corners=True, mode="nearest")[0, 0]
        ok = (depth > 0) & (grid[0].abs() < 1).all(-1) & (dn > 0) & ((z - dn).abs() < 0.05 * dn)
        n = int(ok.sum())
        loss = torch.where(ok, (c - color).abs().mean(-1), 0) + torch.where(ok, (z - d).abs(), 0)
        (loss.sum() / max(n, 1)).backward()
        assert T.grad is not None
        x = adam.step(x, pose_gradient(x, start, T.grad.double().numpy()))
    return orthonormalize(invert_transform(pose_increment(x) @ start))


def single(
    config: SlamConfig, frames: list[Frame], intrinsics: Intrinsics, gap: int, dense: bool
) -> dict[str, Any]:
    """The `single` and `dense` modes."""
    config = config.with_overrides(**{"prune.stages": ()})
    truth = [np.asarray(f.T_world_cam) for f in frames]
    rows: dict[str, list[float]] = {"behind": [], "ahead": []}
    for t in range(max(2, gap), len(frames) - gap, 3):
        guess = constant_velocity(truth[t - 1], truth[t - 2])
        for name, j in (("behind", t - gap), ("ahead", t + gap)):
            if dense:
                est = dense_align(frames[t], frames[j], intrinsics, guess, config.tracking)
            else:
                system = SlamSystem(config, intrinsics, total_frames=None)
                system.process(frames[j])
                est = tracked(system, frames[t], guess)
            rows[name].append(towards(est, truth[t], truth[j]))
    return {k: {**summary(v), "per_frame": [round(x, 4) for x in v]} for k, v in rows.items()}


def centre_offsets(system: SlamSystem, frame: Frame, K: Intrinsics) -> dict[str, float]:
    """The map's centres against `frame`'s observed depth: centre depth minus the depth at its
    pixel (mm; positive = behind the surface), over centres within 10 cm of it."""
    means = np.asarray(system.gaussian_map().means, dtype=np.float64)
    assert frame.T_world_cam is not None
    cam = transform_points(invert_transform(frame.T_world_cam), means)
    z = cam[:, 2]
    front = z > 0.05
    zs = np.where(front, z, 1.0)
    u = np.round(K.fx * cam[:, 0] / zs + K.cx).astype(int)
    v = np.round(K.fy * cam[:, 1] / zs + K.cy).astype(int)
    H, W = frame.depth.shape
    ok = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    observed = np.zeros_like(z)
    observed[ok] = frame.depth[v[ok], u[ok]]
    ok &= (observed > 0) & (np.abs(z - observed) < 0.10)
    return spread_mm(z[ok] - observed[ok])


def spread_mm(values: np.ndarray | torch.Tensor) -> dict[str, float]:
    """Median, 10th and 90th percentiles (mm) of offsets in metres."""
    mm = 1000 * np.asarray(values, dtype=np.float64)
    p10, p50, p90 = np.percentile(mm, [10, 50, 90])
    return {"median_mm": round(p50, 2), "p10_mm": round(p10, 2), "p90_mm": round(p90, 2)}


def pull(config: SlamConfig, frames: list[Frame], intrinsics: Intrinsics) -> dict[str, Any]:
    """The `pull` mode: which pixels of frame t make the map of the frames before it (true
    poses) look as if seen from behind the camera."""
    config = config.with_overrides(**{"tracking.use_ground_truth": True, "prune.stages": ()})
    system = SlamSystem(config, intrinsics, total_frames=None)
    curves: dict[str, np.ndarray] = {}
    for t, frame in enumerate(frames):
        if t >= 2:
            truth, previous = np.asarray(frame.T_world_cam), np.asarray(frames[t - 1].T_world_cam)
            inputs = RenderInputs(*(x.detach() for x in system.mapper.params.render_inputs()))
            color, depth = frame_tensors(frame, system.device)
            outs = []
            for offset in PULL_OFFSETS:
                T = truth.copy()
                T[:3, 3] -= offset * (truth[:3, 3] - previous[:3, 3])
                pose = torch.as_tensor(invert_transform(T), dtype=torch.float32)
                outs.append(render(*inputs, intrinsics, pose))
            at = outs[PULL_OFFSETS.index(0.0)]
            mask = tracking_mask(at.silhouette, depth, config.tracking.silhouette_min)
            edges = depth_steps(frame.depth, 0.05)
            change = (outs[-1].color - at.color).abs().sum(-1)
            textured = change > change[mask].quantile(0.75)
            classes = {
                "all": mask,
                "depth_steps": mask & edges,
                "flat_textured": mask & ~edges & textured,
                "flat_plain": mask & ~edges & ~textured,
            }
            errors = {  # (per offset: each pixel's L1 error)
                "color": [(o.color - color).abs().mean(-1) for o in outs],
                "depth": [(o.depth_normalized - depth).abs() for o in outs],
            }
            for name, pixels in classes.items():
                n = max(int(pixels.sum()), 1)
                for channel, maps in errors.items():
                    losses = np.array([float(e[pixels].sum()) / n for e in maps])
                    key = f"{channel}_{name}"
                    curves[key] = curves.get(key, 0.0) + losses
        system.process(frame)
    return {key: round(parabola_minimum(np.array(PULL_OFFSETS), c), 4) for key, c in curves.items()}


def parabola_minimum(x: np.ndarray, y: np.ndarray) -> float:
    """Where the parabola through the lowest sample of y(x) and its two neighbours is lowest
    (the end sample itself when the lowest is at an end)."""
    k = int(np.argmin(y))
    if k in (0, len(y) - 1):
        return float(x[k])
    a, b, _ = np.polyfit(x[k - 1 : k + 2], y[k - 1 : k + 2], 2)
    return float(-b / (2 * a)) if a > 0 else float(x[k])


def centres(config: SlamConfig, frames: list[Frame], intrinsics: Intrinsics) -> dict[str, Any]:
    """The `centres` mode."""
    raw = config.with_overrides(**{"mapping.first_frame_iters": 0, "prune.stages": ()})
    system = SlamSystem(raw, intrinsics, total_frames=None)
    system.process(frames[0])
    inputs = RenderInputs(*(t.detach() for t in system.mapper.params.render_inputs()))
    assert frames[0].T_world_cam is not None
    T = torch.as_tensor(invert_transform(frames[0].T_world_cam), dtype=torch.float32)
    out = render(*inputs, intrinsics, T)
    _, depth = frame_tensors(frames[0], system.device)
    ok = (out.silhouette > config.tracking.silhouette_min) & (depth > 0)
    edges = depth_steps(frames[0].depth, 0.05)
    residual = out.depth_normalized - depth
    result: dict[str, Any] = {
        "raw_render_flat": spread_mm(residual[ok & ~edges]),
        "raw_render_edges": spread_mm(residual[ok & edges]),
    }
    config = config.with_overrides(**{"tracking.use_ground_truth": True, "prune.stages": ()})
    system = SlamSystem(config, intrinsics, total_frames=None)
    for t, frame in enumerate(frames):
        system.process(frame)
        if t in (0, len(frames) - 1):
            result[f"centres_after_frame_{t}"] = centre_offsets(system, frame, intrinsics)
    scales = np.exp(np.asarray(system.gaussian_map().log_scales, dtype=np.float64))
    result["scale_median_mm"] = round(1000 * float(np.median(scales)), 1)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("seq")
    parser.add_argument(
        "--mode", choices=("loop", "single", "dense", "centres", "pull"), default="loop"
    )
    parser.add_argument("--frames", default="0:24")
    parser.add_argument("--gap", type=int, default=5)
    parser.add_argument("--config", help="YAML on top of the cpu preset")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--edges", type=float, default=0.0, help="loop: leave out depth steps")
    parser.add_argument("--margin", type=float, default=0.0, help="loop: pixels inside t-1")
    parser.add_argument("--consolidate", type=int, default=0, help="loop: iterations first")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = load_config(args.config) if args.config else preset("cpu")
    sequence = open_sequence(args.seq, size=config.size, frames=args.frames)
    frames = list(iter_frames(sequence))
    if args.mode == "loop":
        variant = {"edges": args.edges, "margin": args.margin, "consolidate": args.consolidate}
        result = loop(config, frames, sequence.intrinsics, variant)
        result["variant"] = variant
    elif args.mode == "centres":
        result = centres(config, frames, sequence.intrinsics)
    elif args.mode == "pull":
        result = pull(config, frames, sequence.intrinsics)
    else:
        result = single(config, frames, sequence.intrinsics, args.gap, args.mode == "dense")
    print(json.dumps({"mode": args.mode, "frames": args.frames, "gap": args.gap, **result}))


if __name__ == "__main__":
    main()
