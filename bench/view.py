"""How fluid `gsc view` is on a large map: start-up, slider-to-scene latency, frame rate.

A map of N Gaussians (default 100k) is grown from a SLAM log by tiling its map (each copy
jittered by its Gaussians' own scales, with fresh ids; poses, calibration and stats kept).
Then, with every splat drawn (no subsampling):

- start-up: `gsc view LOG` run as a process, until it prints its address (the map read,
  its covariances computed, the scene ready), against `gsc info LOG` (the same log read and
  summarised) as the baseline; the median of --runs;
- first scene: a headless Chromium (WebGL in software on the CPU: SwiftShader, or Mesa's
  llvmpipe with `--gl llvmpipe`) opening the page, until
  the count shows and the first frame with the splats is rendered;
- slider latency: the keep-ratio and byte-budget sliders moved in the page (typed into their
  boxes), until the page shows the new count (the recoloured splats travel in the same flush);
  the server's own share of it is reported beside;
- frame rate: frames three.js renders per second while the camera orbits (mouse drags).

With `--render server` (`gsc view --render server`) the splats are drawn by the server's
rasterizer and sent to the page as images: the first scene and the sliders wait for the
server's next full-size frame, and the frame rate counts the frames the server sends per
second while the camera orbits (drawn smaller than the page, at the scale that keeps a frame
near `MOTION_FRAME_S`; `--motion-scale` fixes it instead), with their size and the median time
to draw and encode one.

`--draw-only` times the server's drawing alone, without a browser: `ServerRenderer.draw` at
the log's middle pose, at the page's size and at each bound of `MOTION_SCALE_RANGE`, on each
`--devices` (the first is the baseline of the ratios), median of --runs after one warm-up.

Usage:
    python bench/view.py [--source LOG] [--count 100000] [--render browser|server]
        [--json bench/results/view.json]
    python bench/view.py --draw-only [--devices cpu,cuda]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.gaussians import GaussianMap
from gscompress.pipeline.logs import rewrite_map

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_SOURCE = ROOT / "bench_out" / "codec" / "icl-living1.mcap"
"""A SLAM log `bench/codec.py` leaves (any log serves: --source)."""


def tiled(gaussians: GaussianMap, count: int, seed: int = 0) -> GaussianMap:
    """`count` Gaussians: copies of the map, each jittered by its Gaussians' scales, fresh ids."""
    rng = np.random.default_rng(seed)
    copies = -(-count // len(gaussians))
    parts = []
    for k in range(copies):
        jitter = rng.normal(0.0, 1.0, gaussians.means.shape) * gaussians.scales() * (k > 0)
        parts.append(replace(gaussians, means=gaussians.means + jitter))
    ids = np.arange(copies * len(gaussians), dtype=np.uint32).reshape(copies, -1)
    joined = GaussianMap.concat([replace(p, ids=i) for p, i in zip(parts, ids, strict=True)])
    return joined.select(slice(0, count))


def grown_log(source: Path, count: int, out: Path) -> Path:
    """A copy of the log `source` whose map is tiled to `count` Gaussians (made once)."""
    dst = out / f"{source.stem}_{count // 1000}k.mcap"
    if not dst.exists():
        rewrite_map(
            source,
            dst,
            {"name": "bench-tile", "count": count},
            lambda g: (tiled(g, count), {"gaussians": count}),
        )
    return dst


def startup_s(log: Path, runs: int, render: str = "browser") -> dict[str, float]:
    """Median seconds until `gsc view` prints its address, and `gsc info` as the baseline."""
    gsc = str(Path(sys.executable).parent / "gsc")
    view, info = [], []
    for run in range(runs):
        started = time.perf_counter()
        subprocess.run([gsc, "info", str(log)], check=True, capture_output=True)
        info.append(time.perf_counter() - started)
        started = time.perf_counter()
        command = [gsc, "view", str(log), "--port", str(8300 + run), "--render", render]
        proc = subprocess.Popen(
            command, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True
        )
        assert proc.stderr is not None
        for line in proc.stderr:
            if line.startswith("gsc view: http"):
                view.append(time.perf_counter() - started)
                break
        proc.terminate()
        proc.wait(timeout=30)
    return {"view_s": statistics.median(view), "info_s": statistics.median(info)}


def frames_while_orbiting(page: Any, seconds: float) -> float:
    """Frames per second three.js renders while the mouse drags the camera round."""
    counter = "() => window.__viserTestpoints.rendererInfo.render.frame"
    width, height = page.viewport_size["width"], page.viewport_size["height"]
    x, y = width * 0.35, height * 0.5
    page.mouse.move(x, y)
    page.mouse.down()
    first, started = page.evaluate(counter), time.perf_counter()
    step = 0
    while time.perf_counter() - started < seconds:
        step += 1
        page.mouse.move(x + 120 * np.sin(step / 15), y + 40 * np.cos(step / 15))
        page.wait_for_timeout(10)
    frames, elapsed = page.evaluate(counter) - first, time.perf_counter() - started
    page.mouse.up()
    return float(frames / elapsed)


def server_frame_after(viewer: Any, sent: int, timeout_s: float = 120.0) -> None:
    """Wait until the server has sent a full-size frame after its first `sent` ones."""
    renderer = viewer.renderer
    camera = next(iter(viewer.server.get_clients().values())).camera
    deadline = time.perf_counter() + timeout_s
    while time.perf_counter() < deadline:
        full = renderer.last_frame[:2] == (camera.image_width, camera.image_height)
        if renderer.frames_sent > sent and full:
            return
        time.sleep(0.01)
    raise TimeoutError(f"no full-size frame from the server in {timeout_s} s")


def draw_figures(
    log: Path, viewport: tuple[int, int], devices: list[str], runs: int
) -> dict[str, Any]:
    """Seconds `ServerRenderer.draw` takes per frame, by device and frame size."""
    import torch

    from gscompress.camera import rotmat_to_quat
    from gscompress.io.mcap_log import LogReader, read_map
    from gscompress.view.server_render import MOTION_SCALE_RANGE, Layer, ServerRenderer

    g = read_map(log)
    with LogReader(log) as reader:
        _, poses = reader.read_poses()
    T = poses[len(poses) // 2]
    camera = (tuple(rotmat_to_quat(T[:3, :3][None])[0]), tuple(T[:3, 3]), 0.9, *viewport)
    out: dict[str, Any] = {"threads": torch.get_num_threads()}
    if "cuda" in devices:
        out["gpu"] = torch.cuda.get_device_name()
    for device in devices:
        renderer = ServerRenderer(None, device=device)
        renderer.set_layer("map", Layer(g, g.colors(), g.opacities()[:, None]))
        for scale in sorted({1.0, *MOTION_SCALE_RANGE}, reverse=True):
            renderer.draw(camera, scale)  # warm-up (and the layer's tensors made)
            times = []
            for _ in range(runs):
                if device == "cuda":
                    torch.cuda.synchronize()
                started = time.perf_counter()
                renderer.draw(camera, scale)  # (ends with the picture copied to the host)
                times.append(time.perf_counter() - started)
            size = f"{round(viewport[0] * scale)}x{round(viewport[1] * scale)}"
            out[f"draw_s_{device}_{size}"] = statistics.median(times)
    base = devices[0]
    for key in [k for k in out if k.startswith(f"draw_s_{base}_")]:
        for device in devices[1:]:
            other = key.replace(f"_{base}_", f"_{device}_")
            out[f"x_{device}_vs_{base}_{key.rsplit('_', 1)[1]}"] = out[key] / out[other]
    return out


def browser_figures(
    log: Path,
    count: int,
    seconds: float,
    viewport: tuple[int, int],
    render: str = "browser",
    gl: str = "swiftshader",
) -> dict[str, Any]:
    """First scene, slider latencies and frame rate in headless Chromium (WebGL by `gl`)."""
    from gscompress.view import MapViewer, ViewOptions, browser
    from gscompress.view.app import SELECTIONS

    viewer = MapViewer(log, ViewOptions(port=8290, render=render))
    server = viewer.renderer
    out: dict[str, Any] = {}

    def scene_updated(sent: int, version: int) -> None:
        """(In the browser the new colours come with the count shown.) A new picture from the
        server, unless the move left what is drawn as it was."""
        if server is not None and server.version != version:
            server_frame_after(viewer, sent)

    try:
        started = time.perf_counter()
        url = f"http://127.0.0.1:{viewer.port}"
        with browser.open_page(url, *viewport, gl=gl) as (page, errors):
            browser.wait_for_text(page, f"Kept {count:,} of {count:,}", 120)
            out["page_count_shown_s"] = time.perf_counter() - started
            if server is None:
                page.wait_for_function(
                    "() => window.__viserTestpoints && "
                    "window.__viserTestpoints.rendererInfo.render.triangles > 0",
                    timeout=120_000,
                )
            else:
                server_frame_after(viewer, 0)
                out["full_frame"] = list(server.last_frame)
            out["first_frame_s"] = time.perf_counter() - started
            browser.dismiss_notices(page)
            keep_s, keep_server_s = [], []
            for keep in (0.5, 0.3, 0.1, 0.7, 1.0):
                moved = time.perf_counter()
                sent, version = (server.frames_sent, server.version) if server else (0, 0)
                browser.set_slider(page, "Keep ratio", keep)
                kept = int(np.floor(keep * count + 0.5 + 1e-9))
                browser.wait_for_text(page, f"Kept {kept:,} of {count:,}", 60)
                scene_updated(sent, version)
                keep_s.append(time.perf_counter() - moved)
                keep_server_s.append(viewer.last_update_s)
            out["keep_slider_s"] = statistics.median(keep_s)
            out["keep_slider_server_s"] = statistics.median(keep_server_s)
            if server is None:
                out["fps_orbit"] = frames_while_orbiting(page, seconds)
            else:
                out.update(server_orbit(server, page, seconds))
            viewer.selection.value = SELECTIONS[1]  # (as a click in its menu sets it)
            budget_s, budget_server_s = [], []
            for kb in (50, 200, 500, 100):
                moved = time.perf_counter()
                sent, version = (server.frames_sent, server.version) if server else (0, 0)
                browser.set_slider(page, "Budget (kB)", kb)
                browser.wait_for_text(page, f"of {kb * 1000:,} B in", 120)
                scene_updated(sent, version)
                budget_s.append(time.perf_counter() - moved)
                budget_server_s.append(viewer.last_update_s)
            out["budget_slider_s"] = statistics.median(budget_s)
            out["budget_slider_server_s"] = statistics.median(budget_server_s)
            out["console_errors"] = sorted(set(errors))
            renderer = page.evaluate(
                "() => { const g = document.createElement('canvas').getContext('webgl2');"
                " const e = g.getExtension('WEBGL_debug_renderer_info');"
                " return g.getParameter(e ? e.UNMASKED_RENDERER_WEBGL : g.RENDERER); }"
            )
            out["webgl_renderer"] = renderer
    finally:
        viewer.close()
    return out


def server_orbit(server: Any, page: Any, seconds: float) -> dict[str, Any]:
    """The server's frames while the page orbits for `seconds`: their rate, sizes and median
    draw-and-encode time, and the page's own frame rate."""
    sent, began = server.frames_sent, time.perf_counter()
    draws: list[float] = []
    sizes: set[tuple[int, int]] = set()
    orbiting = threading.Event()
    orbiting.set()

    def watch_frames() -> None:
        seen = server.frames_sent
        while orbiting.is_set():
            if server.frames_sent != seen:
                seen = server.frames_sent
                width, height, s = server.last_frame
                draws.append(s)
                sizes.add((width, height))
            time.sleep(0.002)

    watcher = threading.Thread(target=watch_frames)
    watcher.start()
    browser_fps = frames_while_orbiting(page, seconds)
    orbiting.clear()
    watcher.join()
    return {
        "fps_orbit": (server.frames_sent - sent) / (time.perf_counter() - began),
        "orbit_frame_sizes": sorted(sizes),
        "orbit_draw_encode_s_median": statistics.median(draws) if draws else None,
        "page_fps_three_js": browser_fps,
    }


def cpu_model() -> str:
    """The CPU's model name (Linux), else the machine type."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=DEFAULT_SOURCE)
    parser.add_argument("--count", type=int, default=100_000)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=5.0, help="orbiting time for the fps")
    parser.add_argument("--viewport", default="1280x720", help="page size, WIDTHxHEIGHT")
    parser.add_argument("--skip-startup", action="store_true", help="browser figures only")
    parser.add_argument(
        "--draw-only", action="store_true", help="time the server's drawing alone (no browser)"
    )
    parser.add_argument("--devices", default="cpu", help="with --draw-only: e.g. cpu,cuda")
    parser.add_argument(
        "--gl",
        choices=("swiftshader", "llvmpipe"),
        default="swiftshader",
        help="the page's software WebGL (browser.GL_FLAGS)",
    )
    parser.add_argument(
        "--motion-scale",
        type=float,
        default=None,
        help="with --render server: draw moving frames at this fixed scale "
        "(default: adaptive, next_motion_scale)",
    )
    parser.add_argument(
        "--render",
        choices=("browser", "server"),
        default="browser",
        help="where the splats are drawn (gsc view --render)",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "bench_out" / "view")
    parser.add_argument(
        "--json",
        type=Path,
        default=None,
        help="default: bench/results/view.json, view_server.json with --render server",
    )
    args = parser.parse_args()
    if args.json is None:
        name = "view.json" if args.render == "browser" else "view_server.json"
        name = "view_draw.json" if args.draw_only else name
        args.json = ROOT / "bench" / "results" / name
    if not args.source.is_file():
        parser.error(f"no log {args.source}: give one with --source (bench/codec.py makes it)")
    args.out.mkdir(parents=True, exist_ok=True)
    log = grown_log(args.source, args.count, args.out)
    width, height = (int(v) for v in args.viewport.split("x"))
    viewport = (width, height)
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    figures: dict[str, Any] = {
        "commit": commit,
        "machine": f"{cpu_model()}, {os.cpu_count()} cores, no GPU in the browser",
        "log": log.name,
        "gaussians": args.count,
        "viewport": args.viewport,
    }
    if args.draw_only:
        figures.update(draw_figures(log, viewport, args.devices.split(","), args.runs))
    else:
        figures["render"] = args.render
        if not args.skip_startup:
            figures.update(startup_s(log, args.runs, args.render))
        figures["gl"] = args.gl
        if args.motion_scale is not None:
            from gscompress.view import server_render

            server_render.MOTION_SCALE_RANGE = (args.motion_scale, args.motion_scale)
            figures["motion_scale"] = args.motion_scale
        figures.update(
            browser_figures(log, args.count, args.seconds, viewport, args.render, args.gl)
        )
    figures["load_average_1min"] = os.getloadavg()[0]  # (the cores are shared: what else ran)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(figures, indent=2) + "\n")
    print(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
