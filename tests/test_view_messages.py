"""`gsc view`: what a page sends is input. A camera message of an absurd canvas is refused
before anything is drawn (the renderer run under the fuzz policy's memory bound), and a
slider value out of range is refused and put back, so that later pages still get a state."""

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
