"""Pictures of a map at known views: `gsc render` and `gsc eval --save-images`.

Each view the evaluation renders is handed to an `ImageSaver`, which writes, per colouring
asked for, the exact render as an 8-bit PNG (`DIR/<colouring>/<frame index>.png`, as other
tools read it), and with `side_by_side` one labelled figure per view
(`DIR/side_by_side/<frame index>.png`): the observed frame, each colouring with its colour bar,
and the error of the RGB render against the observation.

Colourings:
- `rgb`: the map's own colours (what `gsc eval` scores).
- `importance`: every Gaussian coloured by its PWAS importance (log10 of S / (W + eps)), on the
  perceptual `viridis` map between the 1st and 99th percentiles of the map's positive scores,
  then rendered like the colours: bright where the Gaussians that decide the picture are.
- `depth`: the rendered depth sum_i w_i z_i on `magma`, over the observed frame's valid range.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.camera import Intrinsics
from gscompress.errors import InputError, MapError, OptionError, OutputError
from gscompress.gaussians import GaussianMap
from gscompress.io.files import write_atomic

log = logging.getLogger(__name__)

COLORINGS = ("rgb", "importance", "depth")
"""What a render can be coloured by (`gsc render --color`)."""

IMPORTANCE_CMAP = "viridis"
DEPTH_CMAP = "magma"
ERROR_CMAP = "inferno"
ERROR_MAX = 0.5
"""Top of the error map's colour scale: mean absolute RGB error per pixel, in [0, 1]."""

FIGURE_DPI = 200


def check_colorings(colorings: tuple[str, ...]) -> tuple[str, ...]:
    """The colourings asked for, in order and once each.

    Raises:
        InputError: none, or one that is not in `COLORINGS`.
    """
    unknown = [c for c in colorings if c not in COLORINGS]
    if unknown or not colorings:
        raise InputError(
            f"`color` takes {', '.join(COLORINGS)}; got {', '.join(colorings)}", options=("color",)
        )
    return tuple(dict.fromkeys(colorings))


@dataclass(frozen=True)
class ImageOptions:
    """The views of a sequence a log's map is rendered at, how, and the pictures written of
    them: what `gsc eval` and `gsc render` share (`gscompress.pipeline.evaluate.evaluate_log`).

    Attributes:
        frames: frame subset; None: the one recorded in the log's metadata (else all).
        every: render every `every`-th frame that has a pose (ATE uses all of them).
        size: working size (W, H); None: the one in the log's config, else (a share) the one
            in `poses_from`'s, else the sequence's own.
        poses: a TUM trajectory to render at instead of the log's poses.
        poses_from: another log whose estimated poses to render at instead.
        backend: render backend.
        device: torch device to render on, or "auto".
        lpips: compute LPIPS (reported unavailable with the reason when it cannot be).
        save_images: a folder to write pictures of every view rendered into (`ImageSaver`).
        colorings: what the pictures are coloured by (`COLORINGS`).
        side_by_side: also write one labelled figure per view (observed, render, error).
        force: write into a `save_images` folder that already holds files (else refused).
    """

    frames: str | None = None
    every: int = 1
    size: tuple[int, int] | None = None
    poses: str | Path | None = None
    poses_from: str | Path | None = None
    backend: str = "auto"
    device: str = "auto"
    lpips: bool = True
    save_images: str | Path | None = None
    colorings: tuple[str, ...] = ("rgb",)
    side_by_side: bool = True
    force: bool = False

    def check(self) -> None:
        """Refuse options out of range or at odds with each other, and a `save_images` folder
        that holds files already, without `force`.

        Raises:
            InputError: `every` below 1. OptionError: both `poses` and `poses_from`.
            OutputError: a folder of earlier pictures, without `force`.
        """
        if self.every < 1:
            raise InputError(
                f"`every` must be a positive integer, got {self.every}", options=("every",)
            )
        if self.poses is not None and self.poses_from is not None:
            raise OptionError(
                "`poses` and `poses_from` do not go together: give one source of poses",
                options=("poses", "poses_from"),
            )
        folder = None if self.save_images is None else Path(self.save_images)
        if folder is not None and not self.force and folder.is_dir() and any(folder.iterdir()):
            raise OutputError(
                f"{folder} holds files already; pass `force` to write over them", options=("force",)
            )


@dataclass(frozen=True)
class LogScale:
    """The span of log10 importance a colour map covers: the 1st to the 99th percentile of the
    positive scores (a few dominant Gaussians would squeeze every other colour into one end).
    `gsc render` and `gsc view` colour by it alike."""

    low: float
    high: float

    @classmethod
    def of(cls, scores: np.ndarray) -> LogScale:
        """The span of these scores (zero and negative scores take the lowest colour)."""
        positive = scores[scores > 0]
        if len(positive) == 0:
            return cls(-6.0, 0.0)
        low, high = np.log10(np.percentile(positive, [1.0, 99.0]))
        return cls(float(low), float(max(high, low + 1e-3)))

    def unit(self, scores: np.ndarray) -> np.ndarray:
        """[N] positions in [0, 1] of the scores on this scale."""
        with np.errstate(divide="ignore"):
            logs = np.log10(np.maximum(scores.astype(np.float64), 0.0))
        return np.clip((logs - self.low) / (self.high - self.low), 0.0, 1.0)


def unit_colors(values: np.ndarray, name: str = IMPORTANCE_CMAP) -> np.ndarray:
    """[..., 3] float32 colours of values in [0, 1] on matplotlib's colour map `name` (256
    levels)."""
    from matplotlib import colormaps

    table = colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3].astype(np.float32)
    return table[np.clip(np.round(values * 255), 0, 255).astype(np.int64)]


def colormap(values: np.ndarray, low: float, high: float, name: str) -> np.ndarray:
    """[..., 3] float32 RGB of `values` on the colour map `name`, clipped to [low, high]; NaN
    maps to black."""
    t = np.clip((values - low) / (high - low), 0.0, 1.0)
    rgb = unit_colors(np.nan_to_num(t, nan=0.0), name)
    rgb[np.isnan(values)] = 0.0
    return rgb


def importance_colors(gaussians: GaussianMap) -> tuple[np.ndarray, LogScale]:
    """[N, 3] colour of each Gaussian by its log10 PWAS importance, and the scale it spans.

    Raises:
        MapError: no Gaussian has a positive score (a map without PWAS sums).
    """
    from gscompress.selection import strategy_scores

    scores = strategy_scores(gaussians, "pwas")
    if not (scores > 0).any():
        raise MapError(
            "the map has no PWAS importance (no positive sums): score it first with `gsc score`"
        )
    scale = LogScale.of(scores)
    return unit_colors(scale.unit(scores), IMPORTANCE_CMAP), scale


def to_uint8(image: np.ndarray) -> np.ndarray:
    """[H, W, 3] float in [0, 1] to 8-bit."""
    return np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png(path: Path, image: np.ndarray) -> Path:
    """Write an [H, W, 3] float image in [0, 1] as an 8-bit PNG."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    picture = Image.fromarray(to_uint8(image))
    return write_atomic(path, lambda file: picture.save(file, format="PNG"))


@dataclass
class ImageSaver:
    """Writes the pictures of each rendered view (called by `evaluate_map` as `on_render`).

    Attributes:
        folder: where the PNGs go.
        gaussians: the map rendered.
        intrinsics: the views' camera.
        colorings: the colourings written (`COLORINGS`).
        side_by_side: also write a labelled figure per view: observed, colourings, error.
        backend: render backend (for the colourings other than rgb, rendered again).
        device: torch device.
        title: the figure's title before the frame index (e.g. the log's name).
        written: the files written so far.
    """

    folder: Path
    gaussians: GaussianMap
    intrinsics: Intrinsics
    colorings: tuple[str, ...] = ("rgb",)
    side_by_side: bool = False
    backend: str = "auto"
    device: Any = "cpu"
    title: str = ""
    written: list[Path] = field(default_factory=list)
    _importance: tuple[dict[str, Any], tuple[float, float]] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.colorings = check_colorings(self.colorings)
        for folder in (self.folder, *self.folder.parents):
            if folder.exists() and not folder.is_dir():
                raise InputError(f"cannot write pictures into {self.folder}: {folder} is a file")
        if "importance" in self.colorings:  # refused before any view is rendered
            self._importance_inputs()

    def _importance_inputs(self) -> tuple[dict[str, Any], tuple[float, float]]:
        if self._importance is None:
            import torch

            from gscompress.ops.score import activated_tensors

            colors, scale = importance_colors(self.gaussians)
            params = activated_tensors(self.gaussians, self.device)
            params["colors"] = torch.as_tensor(colors, device=params["means"].device)
            self._importance = params, (scale.low, scale.high)
        return self._importance

    def __call__(self, view: Any, color: np.ndarray, depth: np.ndarray) -> None:
        """Write the pictures of one view: `color` [H, W, 3] and `depth` [H, W], its RGB render."""
        from gscompress.ops.evaluate import render_view

        pictures: dict[str, np.ndarray] = {}
        for coloring in self.colorings:
            if coloring == "rgb":
                pictures[coloring] = color
            elif coloring == "importance":
                params, _ = self._importance_inputs()
                pictures[coloring] = render_view(
                    params, view.T_world_cam, self.intrinsics, self.backend
                )[0]
            else:
                pictures[coloring] = colormap(depth, *self._depth_range(view), DEPTH_CMAP)
        name = f"{int(view.index):06d}.png"
        for coloring, image in pictures.items():
            self.written.append(write_png(self.folder / coloring / name, image))
        if self.side_by_side:
            path = self.folder / "side_by_side" / name
            self.written.append(self._figure(path, view, color, depth, pictures))

    def _depth_range(self, view: Any) -> tuple[float, float]:
        valid = view.depth[view.depth > 0]
        if len(valid) == 0:
            return 0.0, 1.0
        low, high = np.percentile(valid, [1.0, 99.0])
        return float(low), float(max(high, low + 1e-6))

    def _figure(
        self,
        path: Path,
        view: Any,
        color: np.ndarray,
        depth: np.ndarray,
        pictures: dict[str, np.ndarray],
    ) -> Path:
        """Observed frame | each colouring | error map, with titles and colour bars."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        from gscompress.metrics import psnr

        valid = view.depth > 0
        error = np.abs(color - view.color).mean(axis=-1)
        error[~valid] = np.nan  # no observation to compare with
        panels: list[tuple[str, np.ndarray, tuple[str, float, float, str] | None]] = [
            (f"observed frame {view.index}", view.color, None)
        ]
        for coloring, image in pictures.items():
            if coloring == "rgb":
                panels.append(("render", image, None))
            elif coloring == "importance":
                low, high = self._importance_inputs()[1]
                span = (IMPORTANCE_CMAP, low, high, "log10 PWAS importance")
                panels.append(("render coloured by importance", image, span))
            else:
                low, high = self._depth_range(view)
                panels.append(("rendered depth", image, (DEPTH_CMAP, low, high, "depth (m)")))
        score = psnr(color, view.color, valid) if valid.any() else float("nan")
        panels.append(
            (
                f"|render - observed|, PSNR {score:.2f} dB",
                colormap(error, 0.0, ERROR_MAX, ERROR_CMAP),
                (ERROR_CMAP, 0.0, ERROR_MAX, "mean abs. RGB error"),
            )
        )
        height, width = view.color.shape[:2]
        panel_width = 3.2
        fig, axes = plt.subplots(
            1, len(panels), figsize=(panel_width * len(panels), panel_width * height / width + 1.0)
        )
        for ax, (label, image, scale) in zip(np.atleast_1d(axes), panels, strict=True):
            ax.imshow(np.clip(image, 0.0, 1.0), interpolation="nearest")
            ax.set_title(label, fontsize="small")
            ax.set_axis_off()
            if scale is not None:
                cmap, low, high, what = scale
                bar = fig.colorbar(
                    ScalarMappable(Normalize(low, high), cmap),
                    ax=ax,
                    orientation="horizontal",
                    fraction=0.05,
                    pad=0.04,
                )
                bar.set_label(what, fontsize="x-small")
                bar.ax.tick_params(labelsize="x-small")
        if self.title:
            fig.suptitle(f"{self.title}, frame {view.index}", fontsize="medium")
        fig.tight_layout()
        path.parent.mkdir(parents=True, exist_ok=True)
        fmt = path.suffix[1:].lower() or "png"
        write_atomic(path, lambda file: fig.savefig(file, format=fmt, dpi=FIGURE_DPI))
        plt.close(fig)
        return path
