"""What the viewer draws, as arrays: splat covariances and colours, the importance colour map
and its legend, camera frustum poses. numpy only (matplotlib for the colour map, at the point
of use), so it is tested without a browser.
"""

from __future__ import annotations

import numpy as np

from gscompress.camera import rotmat_to_quat
from gscompress.gaussians import GaussianMap
from gscompress.pipeline.images import IMPORTANCE_CMAP, LogScale, unit_colors

COLOUR_MODES = ("rgb", "importance", "opacity", "kept / dropped")
"""What the splats can be coloured by."""

KEPT_RGB = np.array([0.15, 0.75, 0.35], np.float32)
DROPPED_RGB = np.array([0.85, 0.2, 0.2], np.float32)


def legend_image(width: int = 256, height: int = 14, name: str = IMPORTANCE_CMAP) -> np.ndarray:
    """[height, width, 3] uint8 colour bar of the colour map, low scores on the left."""
    row = unit_colors(np.linspace(0.0, 1.0, width), name)
    return np.repeat((row * 255).round().astype(np.uint8)[None], height, axis=0)


def splat_colours(
    gaussians: GaussianMap,
    mode: str,
    kept: np.ndarray,
    scores: np.ndarray | None = None,
    scale: LogScale | None = None,
) -> np.ndarray:
    """[N, 3] float32 colours of the splats.

    Args:
        gaussians: the map.
        mode: one of `COLOUR_MODES`.
        kept: [N] bool, the Gaussians the current selection keeps.
        scores: [N] importance scores (mode "importance").
        scale: the log scale they are drawn on (default: theirs).
    """
    if mode == "rgb":
        return gaussians.colors()
    if mode == "importance":
        if scores is None:
            raise ValueError("colouring by importance needs the scores")
        return unit_colors((scale or LogScale.of(scores)).unit(scores))
    if mode == "opacity":
        return unit_colors(gaussians.opacities().astype(np.float64), "cividis")
    if mode == "kept / dropped":
        return np.where(kept[:, None], KEPT_RGB, DROPPED_RGB).astype(np.float32)
    raise ValueError(f"unknown colour mode {mode!r}; choose one of {', '.join(COLOUR_MODES)}")


def splat_opacities(gaussians: GaussianMap, kept: np.ndarray, hide_dropped: bool) -> np.ndarray:
    """[N, 1] float32 opacities to draw: the map's, 0 for the dropped ones if they are hidden
    (every splat stays in the scene, so the count drawn never changes)."""
    opacities = gaussians.opacities()
    if hide_dropped:
        opacities = np.where(kept, opacities, np.float32(0.0))
    return opacities[:, None].astype(np.float32)


def rgba_words(rgbs: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """[N] uint32 packed RGBA8 (little-endian r, g, b, a bytes), as the splat buffer holds it."""
    rgba = np.concatenate([rgbs, opacities], axis=1)
    return np.ascontiguousarray(np.clip(rgba * 255.0, 0, 255).astype(np.uint8)).view(np.uint32)[
        :, 0
    ]


def frustum_poses(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quaternions [N, 4] (w, x, y, z) and positions [N, 3] of camera-to-world poses
    [N, 4, 4] (the frame a frustum is drawn in: +z forward, +y down)."""
    return rotmat_to_quat(T_world_cam[:, :3, :3]), T_world_cam[:, :3, 3]


def trajectory_segments(T_world_cam: np.ndarray) -> np.ndarray:
    """[N - 1, 2, 3] line segments joining consecutive camera centres."""
    centres = T_world_cam[:, :3, 3].astype(np.float32)
    return np.stack([centres[:-1], centres[1:]], axis=1)
