"""Render a map from known views and score the renders against the observations.

The image half of `gsc eval` (the trajectory half, ATE, is `gscompress.metrics`): every view
is rendered once without gradients, the render's colour is clamped to [0, 1] (what an 8-bit
image of it would hold), and PSNR, SSIM, MS-SSIM, LPIPS and depth L1 are computed against the
observed frame on the pixels with valid observed depth (depth > 0), then averaged over the views
(the mean of per-view values, as SplaTAM and the 3DGS papers report them).

A metric that cannot be computed for these images is reported as unavailable with the reason,
never as a made-up number: MS-SSIM needs images of at least 161 pixels on each side, SSIM at
least 11, LPIPS at least 32 and its weights (`gscompress.metrics.load_lpips`). Depth L1 uses the
rendered depth sum_i w_i z_i (not normalised by the silhouette), the quantity the mapping loss
fits, on the same valid pixels.

Trajectory error is not computed here: it needs no render (`gscompress.metrics.ate_rmse_cm`).

Maps of different agents sit in world frames a few centimetres apart (each is consistent with its
own estimated trajectory), and scored at another agent's poses that offset, not the map, decides
the figures. `refine_poses` separates the two: it moves each view's pose to where the fixed map
explains the frame best, with the SLAM tracker and its loss (`gscompress.slam.tracker.track`),
starting from the given pose; `pose_change` measures how far each moved.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from gscompress.camera import Intrinsics, rotation_angle_deg
from gscompress.errors import InputError
from gscompress.gaussians import GaussianMap
from gscompress.metrics import (
    MS_SSIM_WEIGHTS,
    SSIM_WINDOW,
    LpipsAlex,
    LpipsResult,
    depth_l1_m,
    load_lpips,
    ms_ssim,
    psnr,
    ssim,
)
from gscompress.metrics import lpips as lpips_score
from gscompress.ops.score import activated_tensors, render_at
from gscompress.slam.config import TrackingConfig
from gscompress.slam.keyframes import frame_tensors
from gscompress.slam.params import RenderInputs
from gscompress.slam.tracker import track

METRICS = ("psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm")
"""The image and depth figures of a scored view, each averaged over the views."""

MS_SSIM_MIN_SIDE = (SSIM_WINDOW - 1) * 2 ** (len(MS_SSIM_WEIGHTS) - 1) + 1
"""Smallest image side MS-SSIM accepts (161: the window must fit after 4 downsamplings)."""

LPIPS_MIN_SIDE = 32
"""Smallest image side LPIPS (AlexNet) accepts."""


@dataclass(frozen=True)
class EvalView:
    """One view to evaluate: the observed frame and the pose to render the map from.

    Attributes:
        color: [H, W, 3] observed colour in [0, 1].
        depth: [H, W] observed depth in metres, 0 where invalid.
        T_world_cam: [4, 4] camera-to-world pose to render at.
        index: the frame's index in its sequence (reported per view; -1 when unknown).
        timestamp: the frame's time in seconds (reported per view; NaN when unknown).
    """

    color: np.ndarray
    depth: np.ndarray
    T_world_cam: np.ndarray
    index: int = -1
    timestamp: float = math.nan


def render_view(
    params: dict[str, torch.Tensor],
    T_world_cam: np.ndarray,
    intrinsics: Intrinsics,
    backend: str = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """Render activated Gaussians (see `activated_tensors`) at a pose, without gradients.

    Returns:
        (colour [H, W, 3] float32 clamped to [0, 1], depth [H, W] float32 = sum_i w_i z_i).
    """
    out = render_at(params, T_world_cam, intrinsics, backend)
    color = out.color.clamp(0.0, 1.0).cpu().numpy()
    return color, out.depth.cpu().numpy()


def _size_reasons(intrinsics: Intrinsics) -> dict[str, str]:
    """Why each size-limited metric is unavailable at this image size ("" when it is not)."""
    side = min(intrinsics.width, intrinsics.height)
    size = f"{intrinsics.width}x{intrinsics.height}"

    def need(minimum: int, name: str) -> str:
        if side >= minimum:
            return ""
        return f"{name} needs images of at least {minimum} pixels on each side; these are {size}"

    return {
        "ssim": need(SSIM_WINDOW, "SSIM"),
        "ms_ssim": need(MS_SSIM_MIN_SIDE, "MS-SSIM"),
        "lpips": need(LPIPS_MIN_SIDE, "LPIPS"),
    }


def evaluate_map(
    gaussians: GaussianMap,
    views: Iterable[EvalView],
    intrinsics: Intrinsics,
    *,
    backend: str = "auto",
    device: str | torch.device = "cpu",
    lpips: bool | LpipsAlex = True,
    progress: Callable[[int], object] | None = None,
    on_render: Callable[[EvalView, np.ndarray, np.ndarray], object] | None = None,
) -> dict[str, Any]:
    """Render `gaussians` at every view and score the renders against the observations.

    Args:
        gaussians: the map.
        views: the observed frames and the poses to render them from (consumed once, so a
            generator that loads frames lazily is fine).
        intrinsics: camera intrinsics; the views' images must be `width` x `height`.
        backend: render backend (see `gscompress.render.render`).
        device: torch device to render on.
        lpips: compute LPIPS (True: load the weights; or a loaded `LpipsAlex`); False reports
            it unavailable ("not asked for").
        progress: called with 1 after each view.
        on_render: called with (view, colour [H, W, 3], depth [H, W]) of each view rendered
            (e.g. to save pictures of it).

    Returns:
        A JSON-ready dict. For each of `psnr`, `ssim`, `ms_ssim`, `lpips`, `depth_l1_cm`: the
        mean over the evaluated views, or None with the reason in `<name>_reason` ("" when
        available). `views` is the number of views scored, `views_without_depth` the number
        left out because no pixel had valid observed depth, and `per_view` lists, per scored
        view, its `index`, `timestamp` and each available metric.

    Raises:
        InputError: a view whose images do not match the intrinsics' size.
    """
    reasons = _size_reasons(intrinsics)
    model: LpipsAlex | None = None
    if isinstance(lpips, LpipsAlex):
        model = lpips
    elif not lpips:
        reasons["lpips"] = "not asked for (--no-lpips)"
    elif not reasons["lpips"]:
        loaded = load_lpips()
        if isinstance(loaded, LpipsResult):
            reasons["lpips"] = loaded.reason
        else:
            model = loaded
    if model is None and not reasons["lpips"]:
        reasons["lpips"] = "LPIPS model not available"

    params = activated_tensors(gaussians, device)
    shape = (intrinsics.height, intrinsics.width)
    per_view: list[dict[str, Any]] = []
    without_depth = 0
    for view in views:
        if view.color.shape != (*shape, 3) or view.depth.shape != shape:
            raise InputError(
                f"view {view.index}: images are {view.color.shape[1]}x{view.color.shape[0]}, "
                f"the intrinsics {intrinsics.width}x{intrinsics.height}"
            )
        valid = view.depth > 0
        if not valid.any():
            without_depth += 1
            if progress is not None:
                progress(1)
            continue
        color, depth = render_view(params, view.T_world_cam, intrinsics, backend)
        if on_render is not None:
            on_render(view, color, depth)
        record: dict[str, Any] = {
            "index": int(view.index),
            "timestamp": None if math.isnan(view.timestamp) else float(view.timestamp),
            "psnr": psnr(color, view.color, valid),
            "depth_l1_cm": depth_l1_m(depth, view.depth) * 100.0,
        }
        if not reasons["ssim"]:
            record["ssim"] = ssim(color, view.color, valid)
        if not reasons["ms_ssim"]:
            record["ms_ssim"] = ms_ssim(color, view.color, valid)
        if model is not None:
            record["lpips"] = lpips_score(color, view.color, valid, model=model).value
        per_view.append(record)
        if progress is not None:
            progress(1)

    result: dict[str, Any] = {"views": len(per_view), "views_without_depth": without_depth}
    result.update(mean_metrics(per_view, reasons))
    result["per_view"] = per_view
    return result


def mean_metrics(per_view: list[dict[str, Any]], reasons: dict[str, str]) -> dict[str, Any]:
    """Each of `METRICS` averaged over the views scored, or None with the reason in
    `<name>_reason` ("" when available; `reasons` gives why a metric was not computed)."""
    result: dict[str, Any] = {}
    for name in METRICS:
        reason = reasons.get(name, "")
        if not per_view and not reason:
            reason = "no view was evaluated"
        values = [r[name] for r in per_view if name in r]
        result[name] = float(np.mean(values)) if values and not reason else None
        result[f"{name}_reason"] = reason
    return result


def refine_poses(
    gaussians: GaussianMap,
    views: Iterable[EvalView],
    intrinsics: Intrinsics,
    config: TrackingConfig,
    *,
    backend: str = "auto",
    device: str | torch.device = "cpu",
    progress: Callable[[int], object] | None = None,
) -> list[np.ndarray]:
    """Each view's pose refined against the fixed map: `config.iters` tracking iterations
    (pose only, the map unchanged) from the view's `T_world_cam`.

    A view without valid depth (no pixel passes the tracking mask) keeps its pose.

    Args:
        gaussians: the map, held fixed.
        views: the observed frames and the poses to start from (consumed once).
        intrinsics: camera intrinsics of the views.
        config: the tracker's settings (iterations, learning rates, loss).
        backend: render backend.
        device: torch device to track on.
        progress: called with 1 after each view.

    Returns:
        The refined camera-to-world poses [4, 4], one per view, in order.
    """
    inputs = RenderInputs(**activated_tensors(gaussians, device))
    refined: list[np.ndarray] = []
    for view in views:
        color, depth = frame_tensors(view, device)
        result = track(inputs, color, depth, intrinsics, view.T_world_cam, config, backend=backend)
        refined.append(result.T_world_cam)
        if progress is not None:
            progress(1)
    return refined


def pose_change(T_from: np.ndarray, T_to: np.ndarray) -> tuple[float, float]:
    """How far a camera moved between two camera-to-world poses [4, 4]: the distance of its
    centres in centimetres and the angle of the relative rotation in degrees."""
    T_from, T_to = np.asarray(T_from, np.float64), np.asarray(T_to, np.float64)
    shift = float(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3])) * 100.0
    return shift, rotation_angle_deg(T_from[:3, :3].T @ T_to[:3, :3])
