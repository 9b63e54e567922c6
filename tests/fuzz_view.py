"""The viewer fuzz target: what a page of `gsc view` sends, delivered to a running viewer.

An input is a short list of page messages, msgpack-encoded (the encoding viser's websocket
carries): camera messages (wxyz, position, fov, near, far, the canvas size, look_at,
up_direction) and GUI updates of the controls a page can change (sliders, dropdowns,
checkboxes, buttons, the snapshot slider), a control named as the viewer names its attribute.
The edits set fields to edge values (0, negative, NaN, infinities, 1e308, 64-bit integers,
strings, lists, absurd canvases), drop fields, name unknown controls, add properties other
than the value, and repeat, drop or reorder messages.

`read_view` delivers them to one `MapViewer` (`--render server`, a tiny log and a map to
compare; built once per process) the way viser does: a GUI update through the server's own
message handlers (viser's casts and broadcast, then the viewer's callbacks, run in line here),
a camera as the page's camera state that the renderer's page thread draws from
(`ServerRenderer.serve_once`), a redraw whenever the viewer asked for one. A page value the
viewer refuses is a pass; the defects are an exception out of the viewer's code, a value it did
not take without "refused" in its status, and, after the messages, a viewer that no longer
serves: a control outside its range or options, a message a later page would be sent that
does not encode, no picture from a sane camera.
"""

from __future__ import annotations

import asyncio
import atexit
import math
import shutil
import tempfile
import time
import traceback
from concurrent.futures import Future
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from fuzz_mutations import Chooser, byte_mutation

from gscompress.errors import GscError, clipped

SLIDERS = ("keep", "budget", "snapshot_slider")
DROPDOWNS = ("colour", "selection", "strategy", "codec", "compare")
CHECKBOXES = ("hide_dropped", "sums", "show_estimate", "show_truth", "show_frustums")
BUTTONS = ("solve", "write")
CONTROLS = (*SLIDERS, *DROPDOWNS, *CHECKBOXES, *BUTTONS)
"""The viewer's inputs a page can send updates of, by attribute name."""

SANE_CAMERA = ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -3.0), 0.9, 64, 48)
"""(wxyz, position, fov, width, height) that must always give a picture."""

EDGES: tuple[Any, ...] = (
    0,
    -1,
    1,
    2,
    -0.0,
    0.5,
    2.5,
    1e-320,
    1e9,
    1e30,
    -1e6,
    1e308,
    -1e308,
    math.inf,
    -math.inf,
    math.nan,
    2**31,
    2**53 + 1,
    2**63 - 1,
    -(2**63),
    2**64 - 1,
    "",
    "x",
    "nan",
    "1e30",
    "-5",
    "pwas",
    "x" * 10_000,
    None,
    True,
    False,
    [],
    [1.0],
    [1, 2, 3, 4],
    {},
    {"value": 1},
)
"""Values a field of a page's message is set to (what msgpack can carry: no int past 64 bits)."""

CANVASES = (
    (0, 0),
    (1, 1),
    (16, 1),
    (17, 1),
    (1, 5_000_000),
    (5_000_000, 1),
    (400_000, 3),
    (3840, 2160),
    (8192, 4608),
    (2**31, 2**31),
    (-1, 48),
    (64, -48),
)
"""Canvas sizes (width, height) a camera message is set to."""

PROPERTIES = ("min", "max", "step", "options", "visible", "disabled", "label", "hint", "bogus")
"""Properties other than the value that a page's update may name."""


# ---------------------------------------------------------------------- inputs


def valid_messages(c: Chooser) -> bytes:
    """One to four messages a page sends: cameras and GUI updates within range."""
    import msgspec

    return msgspec.msgpack.encode([_valid_message(c) for _ in range(c.integer(1, 4))])


def _valid_message(c: Chooser) -> dict[str, Any]:
    if c.integer(0, 2) == 0:
        return {"camera": _valid_camera(c)}
    name = c.pick(CONTROLS)
    return {"gui": name, "updates": {"value": _valid_value(name, c)}}


def _valid_camera(c: Chooser) -> dict[str, Any]:
    width, height = c.pick(((64, 48), (160, 120), (320, 240), (48, 64), (1024, 600)))
    wxyz = c.pick(((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.9239, 0.0, 0.3827, 0.0)))
    position = [c.integer(-30, 30) / 10 for _ in range(3)]
    return {
        "wxyz": list(wxyz),
        "position": position,
        "fov": c.integer(20, 150) / 100,
        "near": 0.01,
        "far": 1000.0,
        "image_width": width,
        "image_height": height,
        "look_at": [0.0, 0.0, 0.0],
        "up_direction": [0.0, -1.0, 0.0],
    }


def _valid_value(name: str, c: Chooser) -> Any:
    from gscompress.selection import STRATEGIES
    from gscompress.view import app, scene

    options = {
        "colour": scene.COLOUR_MODES,
        "selection": app.SELECTIONS,
        "strategy": STRATEGIES,
        "codec": app.CODECS,
        "compare": app.COMPARE_MODES,
    }
    if name == "keep":
        return c.integer(1, 100) / 100
    if name == "budget":
        return c.integer(4, 5)  # (within the tiny map's range in every codec)
    if name == "snapshot_slider":
        return c.integer(0, 1)
    if name in options:
        return c.pick(options[name])
    return True if name in BUTTONS else bool(c.integer(0, 1))


def mutate_messages(data: bytes, c: Chooser) -> bytes:
    """One to three edits of the messages (one time in eight, a raw byte edit of the whole)."""
    import msgspec

    if c.integer(0, 7) == 0:
        return byte_mutation(data, c)
    messages = msgspec.msgpack.decode(data)
    for _ in range(c.integer(1, 3)):
        edit = c.pick((_edit_camera, _edit_update, _edit_update, _edit_list))
        edit(messages, c)
    return msgspec.msgpack.encode(messages[:8])


def _edit_camera(messages: list[Any], c: Chooser) -> None:
    """A camera's field set to an edge value or dropped, its canvas made absurd, or a rotation
    or position of another length."""
    cameras = [
        m["camera"] for m in messages if isinstance(m, dict) and isinstance(m.get("camera"), dict)
    ]
    if not cameras:
        messages.append({"camera": _valid_camera(c)})
        return
    camera = c.pick(cameras)
    field = c.pick(tuple(camera) or ("fov",))
    kind = c.integer(0, 4)
    if kind == 0:
        camera.pop(field, None)
    elif kind == 1:
        camera["image_width"], camera["image_height"] = c.pick(CANVASES)
    elif kind == 2:
        camera[c.pick(("wxyz", "position"))] = c.pick(([], [0.0] * 4, [1.0] * 3, [1.0] * 5))
    elif kind == 3 and isinstance(camera.get(field), list) and camera[field]:
        camera[field][c.integer(0, len(camera[field]) - 1)] = c.pick(EDGES)
    else:
        camera[field] = c.pick(EDGES)


def _edit_update(messages: list[Any], c: Chooser) -> None:
    """A GUI update's value set to an edge value or another control's, its control unknown,
    another property added, or its updates emptied or replaced."""
    updates = [m for m in messages if isinstance(m, dict) and "gui" in m]
    if not updates:
        name = c.pick(CONTROLS)
        messages.append({"gui": name, "updates": {"value": _valid_value(name, c)}})
        return
    message = c.pick(updates)
    kind = c.integer(0, 5)
    if kind <= 1 and isinstance(message.get("updates"), dict):
        message["updates"]["value"] = c.pick(EDGES)
    elif kind == 2 and isinstance(message.get("updates"), dict):
        message["updates"]["value"] = _valid_value(c.pick(CONTROLS), c)
    elif kind == 3:
        message["gui"] = c.pick(("bogus", "status", "counts", "", 7, None, "0" * 36))
    elif kind == 4 and isinstance(message.get("updates"), dict):
        message["updates"][c.pick(PROPERTIES)] = c.pick(EDGES)
    else:
        message["updates"] = c.pick(({}, [], None, "value", {"value": None, "min": 0}))


def _edit_list(messages: list[Any], c: Chooser) -> None:
    """A message repeated, dropped, moved or replaced by something that is no message."""
    if not messages:
        return
    at = c.integer(0, len(messages) - 1)
    kind = c.integer(0, 3)
    if kind == 0:
        messages[at:at] = [messages[at]] * c.integer(1, 3)
    elif kind == 1:
        del messages[at]
    elif kind == 2:
        messages.append(messages.pop(at))
    else:
        messages[at] = c.pick((None, 1, "camera", [], {"camera": None}, {"gui": "keep"}))


# ---------------------------------------------------------------------- the viewer


class _InLine:
    """Runs the GUI callbacks that viser would hand to its thread pool at once, on the calling
    thread, keeping what they raise (so that a case is deterministic and its defects seen)."""

    def __init__(self) -> None:
        self.raised: list[BaseException] = []

    def submit(self, fn: Any, *args: Any, **kwargs: Any) -> Future[Any]:
        done: Future[Any] = Future()
        try:
            done.set_result(fn(*args, **kwargs))
        except Exception as exc:
            self.raised.append(exc)
            done.set_result(None)
        return done


class Page:
    """A page connected to a running `MapViewer`: its GUI updates go through the server's own
    message handlers (the viewer's callbacks run in line), its camera is kept as viser keeps a
    page's and drawn for by the renderer's page step. What the viewer's code raises is raised."""

    CLIENT_ID = 999_999

    def __init__(self, viewer: Any, loop: asyncio.AbstractEventLoop | None = None) -> None:
        import threading

        from gscompress.view.server_render import PageState

        self.viewer = viewer
        self.inline = _InLine()
        viewer.server.gui._thread_executor = self.inline
        viewer.server._connected_clients[self.CLIENT_ID] = SimpleNamespace(client_id=self.CLIENT_ID)
        self.loop = loop or asyncio.new_event_loop()
        self.state = PageState(threading.Event())
        self.camera = SimpleNamespace()
        self.notes: list[str] = []
        self.frames: list[Any] = []
        self.client = SimpleNamespace(
            client_id=self.CLIENT_ID,
            camera=self.camera,
            scene=SimpleNamespace(
                set_background_image=lambda image, **_: self.frames.append(image)
            ),
            add_notification=lambda title, body: self.notes.append(f"{title}: {body}"),
        )

    def close(self) -> None:
        """Close its event loop."""
        self.loop.close()

    def update(self, uuid: str, updates: Any) -> None:
        """Send a GUI update message (`updates` as the page wrote it) for the input `uuid`."""
        from viser._messages import GuiUpdateMessage

        message = GuiUpdateMessage(uuid, updates)  # (viser decodes without checking types)
        handlers = self.viewer.server._websock_server
        try:
            self.loop.run_until_complete(handlers._handle_incoming_message(self.CLIENT_ID, message))
        except Exception as exc:  # viser's own handler dropped it, unless the viewer raised
            frames = traceback.extract_tb(exc.__traceback__)
            if any("/gscompress/" in frame.filename for frame in frames):
                raise
        if self.inline.raised:
            raised, self.inline.raised[:] = self.inline.raised[0], []
            raise raised

    def show(self, message: dict[str, Any]) -> None:
        """A camera message (as viser's handler stores it), drawn for this page."""
        import numpy as np

        fields = ("wxyz", "position", "fov", "image_width", "image_height")
        if not all(f in message for f in fields):
            return  # (a message missing fields is not decoded by viser)
        try:
            wxyz, position = np.array(message["wxyz"]), np.array(message["position"])
        except ValueError:  # (viser's handler raises the same: the message is dropped)
            return
        self.camera.wxyz, self.camera.position = wxyz, position
        self.camera.fov = message["fov"]
        self.camera.image_width = message["image_width"]
        self.camera.image_height = message["image_height"]
        self.state.moved_at = time.perf_counter() - 1.0  # (still: drawn at full size)
        renderer = self.viewer.renderer
        assert renderer is not None
        raised: list[Exception] = []

        def draw(camera: Any, scale: float) -> Any:
            try:
                return type(renderer).draw(renderer, camera, scale)
            except Exception as exc:  # (the page step logs it and goes on: a defect here)
                raised.append(exc)
                raise

        renderer.draw = draw  # type: ignore[method-assign]
        try:
            renderer.serve_once(self.client, self.state)
        finally:
            del renderer.draw
        if raised:
            raise raised[0]

    def redraw_if_asked(self) -> None:
        """What the viewer's worker does when a control asked for a redraw."""
        if self.viewer._wanted.is_set():
            self.viewer._wanted.clear()
            self.viewer._work_once()


class _Viewer:
    """One viewer for the whole process, its controls as a page first finds them, and the
    page the cases write from."""

    def __init__(self) -> None:
        from test_view import write_tiny_log

        from gscompress.gaussians import random_map
        from gscompress.io.map_files import write_map_file
        from gscompress.view import MapViewer, ViewOptions

        self.folder = Path(tempfile.mkdtemp(prefix="gsc-fuzz-view-"))
        atexit.register(shutil.rmtree, self.folder, True)
        log = self.folder / "tiny.mcap"
        write_tiny_log(log, n=120)
        other = self.folder / "other.ply"
        write_map_file(random_map(40, seed=2), other)
        self.out = self.folder / "out"
        self.out.mkdir()
        options = ViewOptions(port=0, compare=other, out_dir=self.out, render="server")
        self.viewer = viewer = MapViewer(log, options)
        atexit.register(viewer.close)
        viewer.frustums_drawn.join()
        viewer._closed = True  # the worker stops: each case redraws as it would, in line
        viewer._wanted.set()
        viewer._worker.join()
        self.controls = {name: getattr(viewer, name) for name in CONTROLS}
        self.initial = {
            name: (h.value, getattr(h, "min", None), getattr(h, "max", None))
            for name, h in self.controls.items()
            if name not in BUTTONS
        }
        self.options = {name: tuple(self.controls[name].options) for name in DROPDOWNS}
        self.loop = asyncio.new_event_loop()
        atexit.register(self.loop.close)

    def new_page(self) -> Page:
        """The controls as a page that just connected finds them, no files written, and that
        page."""
        for name, (value, low, high) in self.initial.items():
            handle = self.controls[name]
            if name in DROPDOWNS:
                handle.options = self.options[name]
            if name in SLIDERS and name != "budget":
                handle.min, handle.max = low, high
            handle.value = value
        self.viewer._on_codec()
        page = Page(self.viewer, self.loop)
        page.redraw_if_asked()
        self.viewer.status.content = ""
        for path in self.out.iterdir():
            path.unlink()
        return page


_VIEWER: list[_Viewer] = []


def read_view(path: Path) -> None:
    """Deliver the page's messages to the viewer, then check that it still serves."""
    import msgspec

    if not _VIEWER:
        _VIEWER.append(_Viewer())
    v = _VIEWER[0]
    page = v.new_page()
    try:
        messages = msgspec.msgpack.decode(path.read_bytes())
    except msgspec.DecodeError:  # (viser drops what does not decode, and that page with it)
        messages = []
    refused = []
    for message in messages if isinstance(messages, list) else []:
        if isinstance(message, dict) and isinstance(message.get("camera"), dict):
            page.show(message["camera"])
        elif isinstance(message, dict) and "gui" in message:
            refused += _update(v, page, message["gui"], message.get("updates"))
        page.redraw_if_asked()
    _still_serves(v)
    refused += page.notes
    if refused:  # (a pass: counted apart from the messages taken)
        raise GscError(f"the viewer refused {len(refused)} of the page's messages: {refused[0]}")


def _update(v: _Viewer, page: Page, name: Any, updates: Any) -> list[str]:
    """A page's GUI update of the control `name`; a value not taken must leave "refused" in the
    status. Returns the status when it says so."""
    handle = v.controls.get(name) if isinstance(name, str) else None
    before = handle.value if handle is not None else None
    v.viewer.status.content = ""
    page.update(handle._impl.uuid if handle is not None else str(name), updates)
    said = v.viewer.status.content
    if handle is None or name in BUTTONS or not isinstance(updates, dict) or not updates:
        return [said] if "refused" in said else []  # (no request viser can read)
    taken = set(updates) == {"value"} and _same(handle.value, updates["value"], before)
    if not taken:
        assert "refused" in said, (
            f"{name}: the page's {clipped(updates)} was not taken ({before!r} -> "
            f"{clipped(handle.value)}) and the status says {said!r}"
        )
    return [said] if "refused" in said else []


def _same(value: Any, sent: Any, before: Any) -> bool:
    """Whether a control's `value` is what the page `sent` (as viser casts it)."""
    try:
        return bool(value == type(before)(sent))
    except (TypeError, ValueError, OverflowError):
        return False


def _still_serves(v: _Viewer) -> None:
    """After the messages: every control within its range and options, every message a page
    that connects now is sent encodes, and a sane camera gives a picture."""
    import msgspec
    import numpy as np

    viewer = v.viewer
    for name, handle in v.controls.items():
        msgspec.msgpack.encode(handle.value)
        if name in SLIDERS:
            low, high = v.initial[name][1:] if name != "budget" else (1, 10_000)
            assert low <= handle.min <= handle.value <= handle.max <= high, (
                f"{name}: {handle.value!r} in [{handle.min!r}, {handle.max!r}]"
            )
        elif name in DROPDOWNS:
            assert tuple(handle.options) == v.options[name], f"{name}: {handle.options!r}"
            assert handle.value in v.options[name], f"{name}: {handle.value!r}"
        elif name in CHECKBOXES:
            assert isinstance(handle.value, bool), f"{name}: {handle.value!r}"
    buffer = viewer.server._websock_server._broadcast_buffer
    with buffer.buffer_lock:
        persistent = list(buffer.message_from_id.values())
    for message in persistent:
        msgspec.msgpack.encode(message.as_serializable_dict([]))
    renderer = viewer.renderer
    assert renderer is not None
    image = renderer.draw(SANE_CAMERA, 1.0)
    assert image is not None and image.shape == (48, 64, 3) and image.dtype == np.uint8
