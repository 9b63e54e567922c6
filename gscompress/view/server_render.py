"""The map drawn on the server (`gsc view --render server`): every browser gets the project's
own rasterizer's picture of the splats as its scene's background image, JPEG over the page's
websocket, and draws only the rest (trajectories, cameras, controls) itself.

A browser without a GPU draws splats in software WebGL, a cost per splat that no resolution
saves (too slow to follow the camera on a large map: docs/viewer.md, "Speed on a 100k-Gaussian
map"). The server's renderer (C++ kernels on the CPU, gsplat on CUDA) draws the same splats in a
fraction of that, so the page follows the camera. While the camera moves, frames are drawn
smaller than the page: at the scale that keeps one frame (drawn and encoded) near
`MOTION_FRAME_S`, between the bounds of `MOTION_SCALE_RANGE` (`next_motion_scale`); once the
camera has stood still for `SETTLE_S`, one frame at full size follows. Every Gaussian is drawn
in both.

The browser's camera is OpenCV's (+z forward, +y down; viser's `wxyz` and `position` are its
camera-to-world pose), as is the renderer's, so no axis is flipped on the way.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from gscompress.camera import Intrinsics, quat_to_rotmat
from gscompress.gaussians import GaussianMap
from gscompress.pipeline.images import to_uint8

log = logging.getLogger(__name__)

MOTION_SCALE = 0.5
"""Image size, as a fraction of the page's, of a page's first frames while its camera moves
(later ones follow `next_motion_scale`)."""

MOTION_SCALE_RANGE = (0.25, 1.0)
"""Smallest and largest image size, as a fraction of the page's, while the camera moves."""

MOTION_FRAME_S = 1 / 15
"""Seconds one frame may take to draw and encode while the camera moves (15 frames a second)."""

SETTLE_S = 0.25
"""Seconds without a camera update after which the camera counts as still (a full-size
frame follows)."""

JPEG_QUALITY = 85
"""Quality of the JPEG frames sent to the page."""

MAX_PIXELS = 1920 * 1080
"""The most pixels a frame is drawn with, whatever size a page reports (a larger page gets its
frames scaled down to this); docs/viewer.md says why this size: what a frame takes to draw on
the CPU stays within what the fuzz policy allows a page message."""

FOV_RANGE = (math.radians(1.0), math.radians(170.0))
"""Vertical fields of view drawn; a page's outside them is clamped."""


MAX_ASPECT = 16.0
"""The most a page's canvas may be wider than tall or taller than wide: a camera message beyond
it describes no window, and is refused."""

MIN_SIDE = 16
"""The fewest pixels a frame is drawn with along a side."""


def page_intrinsics(fov: float, width: int, height: int, scale: float = 1.0) -> Intrinsics:
    """Pinhole intrinsics of the page's camera: vertical field of view `fov` (radians, within
    `FOV_RANGE`), the canvas `width` x `height`, drawn at `scale` of that size (at least
    `MIN_SIDE` pixels a side, at most `MAX_PIXELS` in all, the minimum included)."""
    width, height = max(1, width), max(1, height)
    scale = min(scale, math.sqrt(MAX_PIXELS / (width * height)))
    w, h = max(MIN_SIDE, round(width * scale)), max(MIN_SIDE, round(height * scale))
    if w >= h:  # (the minimum side can take the product over: the longer side gives way)
        w = min(w, MAX_PIXELS // h)
    else:
        h = min(h, MAX_PIXELS // w)
    f = 0.5 * h / math.tan(0.5 * min(max(fov, FOV_RANGE[0]), FOV_RANGE[1]))
    return Intrinsics(fx=f, fy=f, cx=0.5 * w, cy=0.5 * h, width=w, height=h)


def next_motion_scale(scale: float, seconds: float) -> float:
    """The image scale for the next frame while the camera moves, after one at `scale` took
    `seconds`: the pixels scaled by `MOTION_FRAME_S / seconds` (a frame's time taken as
    proportional to its pixels, so its side to the square root), within `MOTION_SCALE_RANGE`.
    A server that draws fast (a GPU, a small map) moves at full size; a slow one at a quarter."""
    low, high = MOTION_SCALE_RANGE
    timed = math.isfinite(seconds) and seconds > 0
    return min(max(scale * math.sqrt(MOTION_FRAME_S / seconds) if timed else scale, low), high)


def is_camera(camera: tuple[Any, ...]) -> bool:
    """Whether a page's (wxyz, position, fov, width, height) describes a camera to draw from:
    finite numbers, a non-zero rotation, a size of at least one pixel, an aspect within
    `MAX_ASPECT`. (A page's messages are input like any other: `--host 0.0.0.0` serves any
    machine that reaches this one.)"""
    return camera_refusal(camera) is None and _has_size(camera)


def camera_refusal(camera: tuple[Any, ...]) -> str | None:
    """Why a page's camera message is refused, or None when it is drawn or has no size yet (a
    page before its layout)."""
    try:
        wxyz, position, fov, width, height = camera
        values = [*wxyz, *position, fov, width, height]
        if not all(isinstance(v, int | float | np.number) for v in values):
            raise TypeError  # (numpy would read "16" as a number, and the size checks fail)
        numbers = np.array(values, np.float64)
    except (TypeError, ValueError, OverflowError):
        return "not a camera (wxyz, position, fov, width, height)"
    if len(wxyz) != 4 or len(position) != 3 or not np.all(np.isfinite(numbers)):
        return "a camera of numbers that are not finite"
    if not np.any(numbers[:4]):
        return "a camera of a zero rotation"
    if _has_size(camera) and max(width / height, height / width) > MAX_ASPECT:
        return (
            f"a canvas of {int(width)}x{int(height)} pixels: wider than tall, or taller than "
            f"wide, by more than {MAX_ASPECT:g} times"
        )
    return None


def _has_size(camera: tuple[Any, ...]) -> bool:
    """Whether a finite camera message has a canvas of at least one pixel a side."""
    return bool(camera[3] >= 1 and camera[4] >= 1)


def page_pose(wxyz: Any, position: Any) -> np.ndarray:
    """[4, 4] camera-to-world pose of the page's camera (its `wxyz` rotation and `position`)."""
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(np.asarray(wxyz, np.float64)[None])[0]
    T[:3, 3] = np.asarray(position, np.float64)
    return T


Offset = tuple[float, float, float]


@dataclass
class Layer:
    """One map as the page shows it: its Gaussians, the colours and opacities drawn (a
    colouring, hidden dropped Gaussians), whether it is shown, and where (an offset)."""

    gaussians: GaussianMap
    rgbs: np.ndarray
    opacities: np.ndarray
    visible: bool = True
    offset: Offset = (0.0, 0.0, 0.0)


@dataclass
class PageState:
    """What the renderer knows of one page."""

    wake: threading.Event
    moved_at: float = 0.0
    drawn: tuple[Any, ...] | None = None
    motion_scale: float = MOTION_SCALE
    refused: tuple[Any, ...] | None = None


class ServerRenderer:
    """Draws the visible layers for each connected page, on a thread of its own per page.

    Attributes:
        frames_sent: frames sent to all pages so far.
        last_frame: (width, height, seconds to draw and encode) of the last frame sent.
    """

    def __init__(self, server: Any | None, device: str = "auto"):
        """Draw for the pages of the viser `server` (None: only when `draw` is called)."""
        self._device = device
        self._layers: dict[str, Layer] = {}
        self._version = 0
        self._inputs: tuple[int, dict[str, Any] | None] = (-1, None)
        self._lock = threading.Lock()
        self._closed = False
        self._clients: dict[int, PageState] = {}
        self.frames_sent = 0
        self.last_frame: tuple[int, int, float] = (0, 0, 0.0)
        if server is not None:
            server.on_client_connect(self._connect)
            server.on_client_disconnect(self._disconnect)

    @property
    def version(self) -> int:
        """How many times the layers have changed (each change is drawn again)."""
        return self._version

    def close(self) -> None:
        """Stop drawing (the page threads end at their next wake-up)."""
        self._closed = True
        for state in list(self._clients.values()):
            state.wake.set()

    def set_layer(self, name: str, layer: Layer) -> None:
        """Show `layer` as `name` (replacing the one of that name)."""
        with self._lock:
            self._layers[name] = layer
            self._changed()

    def show(self, name: str, visible: bool, offset: Offset = (0.0, 0.0, 0.0)) -> None:
        """Show or hide the layer `name` (if there is one), at `offset`."""
        with self._lock:
            layer = self._layers.get(name)
            if layer is None or (layer.visible, layer.offset) == (visible, offset):
                return
            layer.visible, layer.offset = visible, offset
            self._changed()

    def _changed(self) -> None:
        self._version += 1
        for state in self._clients.values():
            state.wake.set()

    # ------------------------------------------------------------------ pages

    def _connect(self, client: Any) -> None:
        state = PageState(threading.Event())
        self._clients[client.client_id] = state

        def moved(_camera: Any) -> None:
            state.moved_at = time.perf_counter()
            state.wake.set()

        client.camera.on_update(moved)
        state.wake.set()
        threading.Thread(
            target=self._serve, args=(client, state), name="gsc-view-render", daemon=True
        ).start()

    def _disconnect(self, client: Any) -> None:
        state = self._clients.pop(client.client_id, None)
        if state is not None:
            state.wake.set()

    def _serve(self, client: Any, state: PageState) -> None:
        """Draw for one page until it goes (`serve_once` at each wake-up)."""
        while not self._closed and client.client_id in self._clients:
            state.wake.wait(timeout=SETTLE_S)
            state.wake.clear()
            self.serve_once(client, state)

    def serve_once(self, client: Any, state: PageState) -> None:
        """Draw for one page from its camera now, if anything changed: at its motion scale
        while its camera moves (each moving frame's time sets the next one's scale), at full
        size once it stands still, and again whenever the layers change."""
        camera = client.camera
        try:
            key = (
                tuple(camera.wxyz),
                tuple(camera.position),
                camera.fov,
                camera.image_width,
                camera.image_height,
            )
        except (AttributeError, TypeError):  # (no camera message from the page yet)
            return
        moving = time.perf_counter() - state.moved_at < SETTLE_S
        scale = state.motion_scale if moving else 1.0
        wanted = (self._version, key, scale)
        # (while moving, a view already drawn, at any scale, is not drawn again)
        if wanted == state.drawn or (moving and (state.drawn or ())[:2] == wanted[:2]):
            return
        started = time.perf_counter()
        try:
            image = self.draw(key, scale)
            if image is not None:
                client.scene.set_background_image(image, format="jpeg", jpeg_quality=JPEG_QUALITY)
        except Exception as exc:  # (one frame that fails must not end the page's drawing)
            log.warning("gsc view: a frame was not drawn: %s", exc)
            image = None
        state.drawn = wanted
        if image is None:
            self._refuse(client, state, key)
            return
        seconds = time.perf_counter() - started
        if moving:
            state.motion_scale = next_motion_scale(scale, seconds)
        self.frames_sent += 1
        self.last_frame = (image.shape[1], image.shape[0], seconds)

    def _refuse(self, client: Any, state: PageState, camera: tuple[Any, ...]) -> None:
        """Say in the log and on the page (once for each refused camera) why a page's camera
        message draws nothing."""
        why = camera_refusal(camera)
        if why is None or state.refused == camera:
            return
        state.refused = camera
        log.warning("gsc view: a page's camera was refused: %s", why)
        client.add_notification("Camera refused", f"Nothing is drawn for {why}.")

    # ------------------------------------------------------------------ drawing

    def draw(self, camera: tuple[Any, ...], scale: float) -> np.ndarray | None:
        """[H, W, 3] uint8 picture of the visible layers from `camera` (wxyz, position, fov,
        width, height) at `scale` of its size; None before the page has a size, and for a
        message that describes no camera (`camera_refusal`)."""
        from gscompress.ops.evaluate import render_view

        if not is_camera(camera):
            return None  # (no size yet, or a message that describes no camera)
        wxyz, position, fov, width, height = camera
        params = self._render_inputs()
        intrinsics = page_intrinsics(float(fov), int(width), int(height), scale)
        if params is None:
            return np.zeros((intrinsics.height, intrinsics.width, 3), np.uint8)
        color, _ = render_view(params, page_pose(wxyz, position), intrinsics)
        return to_uint8(color)

    def _render_inputs(self) -> dict[str, Any] | None:
        """The renderer's inputs for the visible layers, made once per change of them."""
        from gscompress.ops.score import activated_tensors
        from gscompress.render import resolve_device

        with self._lock:
            version, layers = self._version, [v for v in self._layers.values() if v.visible]
            if self._inputs[0] == version:
                return self._inputs[1]
            parts = []
            device = resolve_device(self._device)
            for layer in layers:
                if len(layer.gaussians) == 0:
                    continue
                params = activated_tensors(layer.gaussians, device)
                params["means"] = params["means"] + params["means"].new_tensor(layer.offset)
                params["colors"] = params["colors"].new_tensor(layer.rgbs[:, :3])
                params["opacities"] = params["opacities"].new_tensor(
                    np.asarray(layer.opacities, np.float32).reshape(-1)
                )
                parts.append(params)
            inputs = None
            if parts:
                import torch

                inputs = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
            self._inputs = (version, inputs)
            return inputs
