"""`gsc view`: what a page sends is input. A camera message of an absurd canvas is refused
before anything is drawn (the renderer run under the fuzz policy's memory bound), a slider
value out of range is refused and put back, and a page's GUI update that sets anything but a
value the input takes is refused before viser stores or broadcasts it, so that later pages
still get a state (the updates sent through viser's own handlers: fuzz_view.Page)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_view import write_tiny_log


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("view") / "tiny.mcap"
    write_tiny_log(path)
    return path


RENDERER = """
from gscompress.gaussians import random_map
from gscompress.view import server_render as sr

g = random_map(200, seed=1)
renderer = sr.ServerRenderer(None, device="cpu")
renderer.set_layer("a", sr.Layer(g, g.colors(), g.opacities()[:, None]))
identity, origin = (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -3.0)
assert renderer.draw((identity, origin, 0.9, 64, 48), 1.0) is not None  # (imports, kernels)
"""


@pytest.mark.parametrize("size", [(5_000_000, 1), (1, 5_000_000), (400_000, 3)])
def test_6_a_canvas_of_absurd_aspect_is_refused_within_the_memory_bound(
    tmp_path: Path, size: tuple[int, int]
) -> None:
    """A page reporting a 5,000,000x1 canvas was drawn at 5,000,000x16 pixels (the pixel cap
    undone by the minimum side): 4 GB. Drawn in a child held to the fuzz policy's bound."""
    from bounded import MEMORY_FLOOR_BYTES, run_python_bounded

    from gscompress.view import server_render as sr

    code = f"assert renderer.draw((identity, origin, 0.9, {size[0]}, {size[1]}), 1.0) is None"
    run = run_python_bounded(RENDERER, code, MEMORY_FLOOR_BYTES, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert 0 <= run.peak_above_base <= run.bound
    camera = ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -3.0), 0.9, *size)
    assert "wider than tall, or taller than wide" in str(sr.camera_refusal(camera))
    K = sr.page_intrinsics(0.9, *size)  # (the cap holds with the minimum side too)
    assert K.width * K.height <= sr.MAX_PIXELS and min(K.width, K.height) >= 1


@pytest.mark.parametrize(
    ("slider", "value"),
    [
        ("budget", 1e30),
        ("budget", -1e6),
        ("budget", 2.5),
        ("keep", -5.0),
        ("keep", 1e308),
        ("keep", float("nan")),
        ("snapshot_slider", 1e9),
    ],
)
def test_7_a_slider_value_out_of_range_is_refused_and_later_pages_get_a_sane_state(
    tiny_log: Path, tmp_path: Path, slider: str, value: float
) -> None:
    """A page's GUI update of the budget to 1e30 was stored as a 100-bit int: every page that
    connected afterwards had its websocket closed (OverflowError serialising the state); keep
    -5, 1e308 and NaN, a budget of -1e6 and snapshot 1e9 were taken silently."""
    pytest.importorskip("viser")
    import msgspec

    from gscompress.view import MapViewer, ViewOptions

    viewer = MapViewer(tiny_log, ViewOptions(port=0, out_dir=tmp_path))
    try:
        handle = getattr(viewer, slider)
        before = handle.value
        handle.value = value  # (as a page's update message sets it)
        assert handle.value == before
        assert "refused" in viewer.status.content
        for control in (viewer.keep, viewer.budget, viewer.snapshot_slider):
            msgspec.msgpack.encode(control.value)  # (what a page that connects later is sent)
            assert control.min <= control.value <= control.max
        viewer._redraw()
        assert viewer.counts.content and "**" not in viewer.counts.content
    finally:
        viewer.frustums_drawn.join()  # (drawn from a thread: done before the server stops)
        viewer.close()


CHANGED_BY_A_PAGE = [
    [("colour", {"value": "False"})],
    [("compare", {"value": "2.5"})],
    [("codec", {"value": "[]"})],
    [("strategy", {"value": "-inf"})],
    [("selection", {"value": True})],
    [("snapshot_slider", {"value": "B"})],
    [("keep", {"value": ""})],
    [("keep", {"value": [0.5]})],
    [("budget", {"max": 1e30}), ("budget", {"value": 1e30})],
    [("keep", {"min": -1e308, "value": -5.0})],
    [("budget", {"value": 5, "visible": 1e30})],
    [("keep", {"step": 0, "value": 0.5})],
    [("show_estimate", {"value": False, "label": "x" * 10_000})],
    [("hide_dropped", {"value": "no"})],
    [("sums", {"disabled": True})],
]


@pytest.mark.parametrize("updates", CHANGED_BY_A_PAGE, ids=lambda u: repr(u)[:60])
def test_7_a_page_sets_only_values_in_range_or_among_the_options(
    tiny_log: Path, tmp_path: Path, updates: list[tuple[str, dict]]
) -> None:
    """GUI updates as viser receives them from a page (its handler, its casts, its broadcast
    to the other pages): a dropdown set to no option of its own drew nothing (ValueError, or a
    GscError out of the codec's callback), a value that is not a number was dropped without a
    word, and a page could set a slider's range (then any value), its step, label or
    visibility, for every page. Each is refused in the page, nothing is stored or sent to the
    other pages, and what a page that connects afterwards is sent encodes."""
    pytest.importorskip("viser")
    import msgspec
    from fuzz_view import Page

    from gscompress.view import MapViewer, ViewOptions

    viewer = MapViewer(tiny_log, ViewOptions(port=0, out_dir=tmp_path))
    page = Page(viewer)
    try:
        viewer.frustums_drawn.join()
        kinds = ("value", "min", "max", "step", "options", "label", "visible", "disabled")
        handles = {name: getattr(viewer, name) for name, _ in updates}
        before = {
            name: {k: getattr(h, k) for k in kinds if hasattr(h, k)} for name, h in handles.items()
        }
        for name, update in updates:
            viewer.status.content = ""
            page.update(handles[name]._impl.uuid, update)
            assert "refused" in viewer.status.content, (name, update)
            page.redraw_if_asked()
        for name, handle in handles.items():
            assert {k: getattr(handle, k) for k in before[name]} == before[name]
        buffer = viewer.server._websock_server._broadcast_buffer
        by_uuid = {h._impl.uuid: h for h in handles.values()}
        for message in list(buffer.message_from_id.values()):
            msgspec.msgpack.encode(message.as_serializable_dict([]))  # (a later page's state)
            if type(message).__name__ == "GuiUpdateMessage" and message.uuid in by_uuid:
                handle = by_uuid[message.uuid]  # (what a later page is sent is the server's)
                assert all(getattr(handle, k) == v for k, v in message.updates.items())
        viewer._redraw()
        assert viewer.counts.content and "**" not in viewer.counts.content
    finally:
        page.close()
        viewer.close()


@pytest.mark.parametrize("size", [("-5", 48), (64, "1e30"), ("nan", "16")])
def test_a_camera_of_a_canvas_in_text_is_refused_and_the_page_still_drawn(
    size: tuple[object, object],
) -> None:
    """A camera message whose canvas size was text of a number ("-5") passed the conversion to
    numbers, then its size check raised TypeError out of the page's drawing step, which ended
    that page's frames (the fuzz target `view` found it)."""
    import threading
    from types import SimpleNamespace

    import numpy as np

    from gscompress.gaussians import random_map
    from gscompress.view import server_render as sr

    camera = ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -3.0), 0.9, *size)
    assert "not a camera" in str(sr.camera_refusal(camera))
    g = random_map(50, seed=1)
    renderer = sr.ServerRenderer(None, device="cpu")
    renderer.set_layer("a", sr.Layer(g, g.colors(), g.opacities()[:, None]))
    frames: list[np.ndarray] = []
    notes: list[str] = []
    page = SimpleNamespace(
        wxyz=np.array(camera[0]),
        position=np.array(camera[1]),
        fov=0.9,
        image_width=size[0],
        image_height=size[1],
    )
    client = SimpleNamespace(
        client_id=1,
        camera=page,
        scene=SimpleNamespace(set_background_image=lambda image, **_: frames.append(image)),
        add_notification=lambda title, body: notes.append(body),
    )
    state = sr.PageState(threading.Event())
    renderer.serve_once(client, state)
    assert not frames and len(notes) == 1 and "not a camera" in notes[0]
    page.image_width, page.image_height = 64, 48  # (the page's next camera is drawn)
    renderer.serve_once(client, state)
    assert len(frames) == 1 and frames[0].shape == (48, 64, 3)
