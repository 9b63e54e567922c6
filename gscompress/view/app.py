"""The viewer's web page (viser): the map as splats, its colourings, the live prune and share
previews, the trajectories, the snapshots and a second map to compare.

Every control only records what it wants; one worker thread redraws from the latest values,
so a dragged slider never queues stale work behind it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.errors import GscError, OptionError, clipped
from gscompress.gaussians import GaussianMap
from gscompress.io.codec import CODECS, DEFAULT_SHARE_CODEC
from gscompress.io.mcap_log import decoded_map
from gscompress.ops.budget import Budget
from gscompress.pipeline.share.cut import ShareCut, smallest_share_bytes
from gscompress.pipeline.share.options import ShareOptions
from gscompress.selection import STRATEGIES
from gscompress.view import cuts, scene
from gscompress.view.server_render import Layer, ServerRenderer
from gscompress.view.source import MapSource

log = logging.getLogger(__name__)

SELECTIONS = ("prune (keep ratio)", "share (byte budget)")
COMPARE_MODES = ("A", "B", "A | B side by side", "B + share of A")
ESTIMATE_RGB = (255, 140, 0)
TRUTH_RGB = (40, 200, 80)


def import_viser() -> Any:
    """The viser module, or an OptionError saying how to install it."""
    try:
        import viser
    except ImportError:
        raise OptionError(
            "gsc view needs viser, the optional [view] extra: pip install 'gscompress[view]'"
        ) from None
    return viser


def page_value_refusal(handle: Any, value: Any, whole: bool = False) -> str | None:
    """Why `value` is refused for the viser input `handle`, or None: a checkbox or a button
    takes true or false, a dropdown one of its options, a slider a finite number within its
    range (`whole`: a whole number)."""
    current = handle.value
    if isinstance(current, bool):
        return None if isinstance(value, bool) else "it takes true or false"
    if isinstance(current, str):
        options = tuple(handle.options)
        fine = isinstance(value, str) and value in options
        return None if fine else f"it takes one of {', '.join(options)}"
    try:
        fine = (
            isinstance(value, int | float)
            and not isinstance(value, bool)
            and math.isfinite(value)
            and handle.min <= value <= handle.max
            and (not whole or float(value).is_integer())
        )
    except OverflowError:  # (an int beyond any float)
        fine = False
    span = f"{handle.min:g} to {handle.max:g}" + (" in whole numbers" if whole else "")
    return None if fine else f"it takes {span}"


def page_title(path: Path, compare: Path | None = None) -> str:
    """The browser tab's title and the panel's label: the map's file name (and the one compared
    with it), then the tool."""
    names = path.name if compare is None else f"{path.name} vs {compare.name}"
    if len(names) > 80:  # (a file name may be long)
        names = names[:77] + "..."
    return f"{names} - gsc view"


def _set_page_title(server: Any, title: str) -> None:
    """Name the page `title` instead of "Viser": viser has no call for it, so a line of script
    is sent to every page that connects (the title as a JSON string: a file name cannot break
    out of it). A viser without that message leaves viser's title."""
    import json

    try:
        from viser import _messages

        message = _messages.RunJavascriptMessage(source=f"document.title = {json.dumps(title)};")
        server.scene._websock_interface.queue_message(message)
    except (ImportError, AttributeError, TypeError):
        log.debug("viser cannot set the page title; it stays viser's")


@dataclass(frozen=True)
class ViewOptions:
    """How the viewer is served.

    Attributes:
        host: the address it listens on (127.0.0.1: this machine only).
        port: its port.
        seq: the sequence the log was made from (the solver scores against its frames).
        compare: a second log or map file, shown beside the first or on its own.
        out_dir: where the write buttons put files.
        seed: seed of the random strategy.
        render: where the splats are drawn: "browser" (WebGL in the page) or "server" (the
            project's rasterizer, sent to the page as images; `gscompress.view.server_render`).
        recording: when `seq` is a recording, its topics, pairing and ground truth
            (`gscompress.datasets.RecordingOptions`; None: those the log's run recorded).
    """

    host: str = "127.0.0.1"
    port: int = 8080
    seq: Path | None = None
    compare: Path | None = None
    out_dir: Path = Path(".")
    seed: int = 0
    render: str = "browser"
    recording: Any = None


class MapViewer:
    """A running viewer of one log or map file (and optionally a second to compare).

    Attributes:
        server: the viser server.
        source: the file viewed.
        updates: how many times the splats were redrawn.
        last_update_s: seconds the last redraw took, from the control's change to the scene
            message queued.
    """

    def __init__(self, path: str | Path, options: ViewOptions = ViewOptions()):
        viser = import_viser()
        self.options = options
        self.source = MapSource.open(path)
        self.other = None if options.compare is None else MapSource.open(options.compare)
        self.snapshot = self.source.snapshot_count - 1
        self.gaussians = self.source.snapshot(self.snapshot)
        self.updates, self.last_update_s = 0, 0.0
        self._wanted = threading.Event()
        self._requested_at = 0.0
        self._lock = threading.Lock()
        self._closed = False
        self._drawn: dict[str, Any] = {}
        self._share: cuts.SharePreview | None = None
        self._share_key: tuple[Any, ...] | None = None
        compare = None if options.compare is None else Path(options.compare)
        self.title = page_title(Path(path), compare)
        self.server = viser.ViserServer(
            host=options.host, port=options.port, label=self.title, verbose=False
        )
        _set_page_title(self.server, self.title)
        # (no share button: a map stays on this machine unless a file is sent on purpose)
        self.server.gui.configure_theme(control_width="large", show_share_button=False)
        self.server.scene.set_up_direction("-y")  # (camera frames: +y down, +z forward)
        self.renderer = ServerRenderer(self.server) if options.render == "server" else None
        self.splats: Any = None  # (A's splats in the browser; none when the server draws)
        self._inputs: dict[str, tuple[Any, bool]] = {}
        self._build_gui()
        self._screen_page_updates()
        self._load_map()
        self._draw_trajectories()
        self._place_camera()
        self._redraw()
        self._worker = threading.Thread(target=self._work, name="gsc-view", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ lifecycle

    @property
    def port(self) -> int:
        """The port the viewer listens on."""
        return int(self.server.get_port())

    def close(self) -> None:
        """Stop the server and the worker."""
        self._closed = True
        if self.renderer is not None:
            self.renderer.close()
        self._wanted.set()
        self._worker.join(timeout=5)
        self.server.stop()

    def _request(self, *_args: Any) -> None:
        """Ask the worker to redraw from the controls' latest values."""
        self._requested_at = time.perf_counter()
        self._wanted.set()

    def _work(self) -> None:
        while True:
            self._wanted.wait()
            if self._closed:
                return
            self._wanted.clear()
            self._work_once()

    def _work_once(self) -> None:
        """One redraw from the controls' latest values (a GscError said in the page)."""
        started = self._requested_at
        try:
            self._redraw()
        except GscError as exc:
            self._say(f"**{exc}**")
        self.last_update_s = time.perf_counter() - started

    def _say(self, text: str) -> None:
        self.status.content = text

    # ------------------------------------------------------------------ controls

    def _build_gui(self) -> None:
        gui = self.server.gui
        src = self.source
        gui.add_markdown(
            f"**{src.path.name}**" + (f" vs **{self.other.path.name}**" if self.other else "")
        )
        self.map_info = gui.add_markdown("")
        with gui.add_folder("Colour"):
            self.colour = gui.add_dropdown("Colour by", scene.COLOUR_MODES, initial_value="rgb")
            self.legend = gui.add_image(scene.legend_image(), label="importance", visible=False)
            self.legend_text = gui.add_markdown("", visible=False)
            self.hide_dropped = gui.add_checkbox("Hide dropped", True)
        with gui.add_folder("Prune / share"):
            scored = self.gaussians.has_importance
            self.selection = gui.add_dropdown("Preview", SELECTIONS, initial_value=SELECTIONS[0])
            self.strategy = gui.add_dropdown(
                "Rank by", STRATEGIES, initial_value="pwas" if scored else "opacity"
            )
            self.keep = gui.add_slider("Keep ratio", 0.01, 1.0, 0.01, 1.0)
            self._guard(self.keep)
            # (the smallest codec first)
            self.codec = gui.add_dropdown("Codec", CODECS[::-1], initial_value=DEFAULT_SHARE_CODEC)
            self.sums = gui.add_checkbox("PWAS sums", True)
            self.budget = gui.add_slider("Budget (kB)", 1, 2, 1, 2)
            self._guard(self.budget, whole=True)
            self.counts = gui.add_markdown("")
            self.sizes = gui.add_markdown("")
            self.solve = gui.add_button("Solve codec for this budget", visible=src.is_log)
            self.write = gui.add_button("Write this prune / share")
            self.status = gui.add_markdown("")
        if src.snapshot_count > 1:
            with gui.add_folder("Snapshots"):
                last = src.snapshot_count - 1
                self.snapshot_slider = gui.add_slider("Snapshot", 0, last, 1, last)
                self._guard(self.snapshot_slider, whole=True)
                self.snapshot_slider.on_update(self._on_snapshot)
        if len(src.poses) or len(src.poses_gt):
            with gui.add_folder("Trajectory"):
                self.show_estimate = gui.add_checkbox("Estimated (orange)", True)
                self.show_truth = gui.add_checkbox("Ground truth (green)", len(src.poses_gt) > 0)
                self.show_frustums = gui.add_checkbox("Keyframe cameras", True)
                for box in (self.show_estimate, self.show_truth, self.show_frustums):
                    self._guard(box)
                    box.on_update(self._on_trajectory_visibility)
        self.compare = gui.add_dropdown(
            "Show", COMPARE_MODES, initial_value=COMPARE_MODES[0], visible=self.other is not None
        )
        for handle in (
            self.colour,
            self.hide_dropped,
            self.selection,
            self.strategy,
            self.codec,
            self.sums,
            self.compare,
            self.solve,
            self.write,
        ):
            self._guard(handle)
        for control in (
            self.colour,
            self.hide_dropped,
            self.selection,
            self.strategy,
            self.keep,
            self.codec,
            self.sums,
            self.budget,
            self.compare,
        ):
            control.on_update(self._request)
        self.codec.on_update(self._on_codec)
        self.sums.on_update(self._on_codec)
        self.solve.on_click(self._on_solve)
        self.write.on_click(self._on_write)

    def _guard(self, handle: Any, whole: bool = False) -> None:
        """Hold the input `handle` to the values `page_value_refusal` takes: a page's update of
        anything else is refused before viser stores it (`_screen_page_update`), and any other
        assignment is put back to the last good value. Either refusal is said in the page and
        the log. This runs before the input's other callbacks."""
        self._inputs[handle._impl.uuid] = (handle, whole)
        if hasattr(handle, "on_click"):
            return  # (a button: a click leaves no value to put back)
        good = [handle.value]

        def check(_event: Any) -> None:
            value = handle.value
            why = page_value_refusal(handle, value, whole)
            if why is None:
                good[0] = value
                return
            self._refuse(handle.label, clipped(value), why)
            handle.value = good[0]

        handle.on_update(check)

    def _screen_page_updates(self) -> None:
        """Put `_screen_page_update` ahead of viser's own handler of a page's GUI updates
        (viser offers no public hook before it: its handler stores the update and sends it to
        the other pages before any callback of the input runs)."""
        from viser._messages import GuiUpdateMessage

        handlers = self.server._websock_server._incoming_handlers[GuiUpdateMessage]
        handlers.insert(0, self._screen_page_update)

    def _screen_page_update(self, _client_id: Any, message: Any) -> None:
        """Refuse a page's GUI update of an input unless it sets only its value, to one that
        `page_value_refusal` takes: a refused update is neither stored nor sent to the other
        pages. (A page is input: `--host 0.0.0.0` serves any machine that reaches this one,
        and viser's own handler would set any property a page names, a slider's range
        included, and cast the value to the input's type before any callback runs.)"""
        found = self._inputs.get(message.uuid)
        if found is None:
            return
        handle, whole = found
        updates = message.updates
        if isinstance(updates, dict) and set(updates) == {"value"}:
            shown = clipped(updates["value"])
            why = page_value_refusal(handle, updates["value"], whole)
        else:
            shown, why = clipped(updates), "a page sets an input's value only"
        if why is not None:
            message.uuid, message.updates = "", {}  # (no input has that uuid: viser drops it)
            self._refuse(handle.label, shown, why)

    def _refuse(self, label: str, shown: str, why: str) -> None:
        """Say in the page and the log that a page's update of the input `label` was refused."""
        log.warning("gsc view: a page's %s of %s was refused (%s)", label, shown, why)
        self._say(f"**{label} {shown} refused: {why}**")

    def _budget_range(self) -> None:
        """Fit the budget slider to the map: from the smallest share file to the whole map's,
        in the chosen codec."""
        codec, sums = self.codec.value, self.sums.value
        smallest = smallest_share_bytes(codec)
        how = ShareOptions(codec=codec, sums=sums)
        whole = ShareCut(self.source.path, Budget(ratio=1.0), how, source=self._source_pair())
        whole_bytes = whole.size(len(self.gaussians))
        low, high = int(np.ceil(smallest / 1000)) + 1, max(int(np.ceil(whole_bytes / 1000)), 3)
        self.budget.min, self.budget.max = low, high
        if not low <= self.budget.value <= high:
            self.budget.value = int(np.clip(round(high * 0.1), low, high))

    def _on_codec(self, *_args: Any) -> None:
        with self._lock:
            self._budget_range()
        self._request()

    def _on_snapshot(self, *_args: Any) -> None:
        with self._lock:
            self.snapshot = int(self.snapshot_slider.value)
            self.gaussians = self.source.snapshot(self.snapshot)
            self._load_map()
        self._request()

    # ------------------------------------------------------------------ the map

    def _share_options(self) -> ShareOptions:
        """The share the controls ask for: `gsc share`'s with their strategy, codec and sums,
        and the viewer's seed."""
        return ShareOptions(
            strategy=self.strategy.value,
            codec=self.codec.value,
            sums=self.sums.value,
            seed=self.options.seed,
        )

    def _source_pair(self) -> tuple[GaussianMap, Any]:
        return self.gaussians, self.source.metadata

    def _load_map(self) -> None:
        """Draw the current snapshot: its splats (geometry once; colours by `_redraw`)."""
        g = self.gaussians
        self.scores = g.importance.astype(np.float64) if g.has_importance else None
        self.scale = None if self.scores is None else scene.LogScale.of(self.scores)
        if self.scale is not None:
            self.legend_text.content = (
                f"log10 PWAS score: {self.scale.low:.2f} (left) to {self.scale.high:.2f} "
                "(right), 1st to 99th percentile"
            )
        times = self.source.snapshot_times_ns
        when = f" at {(times[self.snapshot] - times[0]) / 1e9:.1f} s" if len(times) > 1 else ""
        self.map_info.content = (
            f"Snapshot {self.snapshot + 1} of {len(times)}{when}: {len(g):,} Gaussians, "
            f"{'scored' if g.has_importance else 'no PWAS scores'}"
        )
        if self.renderer is None:  # (the browser's splats: their geometry, sent once)
            self._geometry = (g.means, g.covariances().astype(np.float32))
        self._drawn.pop("a", None)
        self._share_key = None
        self._budget_range()
        if self.other is not None and "b" not in self._drawn:
            self.splats_b = self._add_splats("map_b", self.other.snapshot(), visible=False)
            self._drawn["b"] = True

    def _add_splats(self, name: str, g: GaussianMap, visible: bool = True) -> Any:
        """Draw the map `g` in its own colours as the scene node `name` (in the browser), or as
        the server's layer `name`; the node, or None on the server."""
        rgbs, opacities = g.colors(), g.opacities()[:, None]
        if self.renderer is not None:
            self.renderer.set_layer(name, Layer(g, rgbs, opacities, visible))
            return None
        return self.server.scene.add_gaussian_splats(
            f"/{name}",
            centers=g.means,
            covariances=g.covariances().astype(np.float32),
            rgbs=rgbs,
            opacities=opacities,
            visible=visible,
        )

    def _show(self, node: Any, name: str, visible: bool, offset: float = 0.0) -> None:
        """Show or hide a map drawn by `_add_splats` (moved by `offset` along x)."""
        if self.renderer is not None:
            self.renderer.show(name, visible, (offset, 0.0, 0.0))
        elif node is not None:
            node.visible, node.position = visible, (offset, 0.0, 0.0)

    def _current_selection(self) -> np.ndarray:
        """[N] bool: what the chosen preview keeps (and its counts and sizes shown)."""
        g, strategy, seed = self.gaussians, self.strategy.value, self.options.seed
        if self.selection.value == SELECTIONS[0]:
            keep = float(self.keep.value)
            kept = cuts.kept_by_prune(g, keep, strategy, seed)
            self.counts.content = (
                f"Kept {int(kept.sum()):,} of {len(g):,} Gaussians ({kept.mean():.1%}) by "
                f"{strategy}: `gsc prune --keep {keep:g} --by {strategy}`"
            )
            self.sizes.content = ""
            return kept
        budget = Budget.parse(f"{int(self.budget.value)}kB")
        key = (self.snapshot, str(budget), strategy, self.codec.value, self.sums.value)
        if key != self._share_key or self._share is None:
            self._share = cuts.preview_share(
                self.source.path, self._source_pair(), budget, self._share_options()
            )
            self._share_key = key
        share = self._share
        self.counts.content = (
            f"Sent {share.count:,} of {len(g):,} Gaussians ({share.count / len(g):.1%}) by "
            f"{strategy}: {share.file_bytes:,} B of {budget.budget_bytes:,} B in "
            f"{cuts.codec_label(share.codec, share.sums)}: `gsc share --budget {budget}`"
        )
        self.sizes.content = "The same Gaussians in each codec:\n\n" + "\n".join(
            f"- {label}: {size:,} B" for label, size in share.sizes.items()
        )
        return share.kept

    def _redraw(self) -> None:
        """Recolour the splats from the controls (one buffer message when anything changed)."""
        with self._lock:
            try:
                kept = self._current_selection()
            except GscError as exc:
                kept = np.ones(len(self.gaussians), bool)
                self.counts.content = f"**{exc}**"
            mode = self.colour.value
            if mode == "importance" and self.scores is None:
                self._say("**this map has no PWAS scores to colour by**")
                mode = "rgb"
            self.legend.visible = self.legend_text.visible = mode == "importance"
            key = (self.snapshot, mode, self.hide_dropped.value, kept.tobytes())
            if self._drawn.get("a") != key:
                rgbs = scene.splat_colours(self.gaussians, mode, kept, self.scores, self.scale)
                opacities = scene.splat_opacities(self.gaussians, kept, self.hide_dropped.value)
                if self.renderer is not None:
                    self.renderer.set_layer("map_a", Layer(self.gaussians, rgbs, opacities))
                elif "a" not in self._drawn:  # a new map: its geometry with its colours
                    self.splats = self.server.scene.add_gaussian_splats(
                        "/map_a", *self._geometry, rgbs=rgbs, opacities=opacities
                    )
                else:  # the same map: only the colour words change
                    buffer = self.splats.buffer.copy()
                    buffer[:, 7] = scene.rgba_words(rgbs, opacities)
                    self.splats.buffer = buffer
                self._drawn["a"] = key
                self.updates += 1
            self._show_compare()

    def _show_compare(self) -> None:
        """Show A, B, both side by side, or B with A's current share."""
        if self.other is None:
            return
        mode = self.compare.value
        offset = 0.0
        if mode == COMPARE_MODES[2]:
            a, b = self.gaussians.means, self.other.snapshot().means
            offset = float(a[:, 0].max() - b[:, 0].min()) * 1.1 if len(a) and len(b) else 0.0
        self._show(self.splats, "map_a", mode in (COMPARE_MODES[0], COMPARE_MODES[2]))
        self._show(self.splats_b, "map_b", mode != COMPARE_MODES[0], offset)
        share_node = self._drawn.get("share_node")
        if mode != COMPARE_MODES[3]:
            if "share_key" in self._drawn:
                self._show(share_node, "share_on_b", False)
            return
        share = self._share
        if share is None or self.selection.value != SELECTIONS[1]:
            self._say("choose the share preview to see B with A's share")
            return
        received = decoded_map(share.shared, share.codec, sums=share.sums)
        if self._drawn.get("share_key") != self._share_key:
            self._drawn["share_node"] = self._add_splats("share_on_b", received)
            self._drawn["share_key"] = self._share_key
        self._show(self._drawn["share_node"], "share_on_b", True)

    # ------------------------------------------------------------------ trajectories

    def _draw_trajectories(self) -> None:
        src = self.source
        self._trajectory_nodes: dict[str, list[Any]] = {
            "est": [],
            "gt": [],
            "frustums": [],
            "gt_frustums": [],
        }
        for kind, poses, colour in (
            ("est", src.poses, ESTIMATE_RGB),
            ("gt", src.poses_gt, TRUTH_RGB),
        ):
            if len(poses) > 1:
                node = self.server.scene.add_line_segments(
                    f"/trajectory/{kind}",
                    scene.trajectory_segments(poses),
                    colors=colour,
                    thickness=2.0,
                    thickness_units="screen",
                )
                self._trajectory_nodes[kind].append(node)
        if len(src.poses):  # (keyframes may need the SLAM config: seconds, after start-up)
            self.frustums_drawn = threading.Thread(
                target=self._draw_frustums, name="gsc-frustums", daemon=True
            )
            self.frustums_drawn.start()

    def _draw_frustums(self) -> None:
        src = self.source
        keyframes = src.keyframes()
        camera = src.intrinsics
        fov = 2 * np.arctan2(camera.height / 2, camera.fy) if camera else np.pi / 3
        aspect = camera.width / camera.height if camera else 4 / 3
        extent = np.ptp(src.poses[:, :3, 3], axis=0).max() if len(src.poses) > 1 else 1.0
        truth = src.keyframe_truth(keyframes)
        for kind, poses, colour in (
            ("frustums", src.poses[keyframes], ESTIMATE_RGB),
            ("gt_frustums", truth, TRUTH_RGB),
        ):
            wxyz, positions = scene.frustum_poses(poses)
            for i, (q, p) in enumerate(zip(wxyz, positions, strict=True)):
                node = self.server.scene.add_camera_frustum(
                    f"/trajectory/{kind}/{i}",
                    fov=float(fov),
                    aspect=float(aspect),
                    scale=float(max(extent, 0.1) * 0.04),
                    thickness=1.5,
                    thickness_units="screen",
                    color=colour,
                    wxyz=q,
                    position=p,
                )
                self._trajectory_nodes[kind].append(node)
        self._on_trajectory_visibility()

    def _on_trajectory_visibility(self, *_args: Any) -> None:
        frustums = self.show_frustums.value
        shown = {
            "est": self.show_estimate.value,
            "gt": self.show_truth.value,
            "frustums": frustums and self.show_estimate.value,
            "gt_frustums": frustums and self.show_truth.value,
        }
        for kind, nodes in self._trajectory_nodes.items():
            for node in nodes:
                node.visible = shown[kind]

    def _place_camera(self) -> None:
        """Start the browser's camera behind the first pose of the log, looking along it (or,
        without poses, in front of the map)."""
        camera = self.server.initial_camera
        means = self.gaussians.means.astype(np.float64)
        extent = float(np.ptp(means, axis=0).max()) if len(means) else 1.0
        if len(self.source.poses):
            T = self.source.poses[0]
            forward, down = T[:3, 2], T[:3, 1]
            position = T[:3, 3] - (forward + 0.5 * down) * 0.3 * extent
            look_at, up = T[:3, 3] + forward * 0.5 * extent, -down
        else:
            look_at = np.median(means, axis=0) if len(means) else np.zeros(3)
            position = look_at + np.array([0.0, -0.3, -1.2]) * extent
            up = np.array([0.0, -1.0, 0.0])
        camera.position = tuple(float(v) for v in position)
        camera.look_at = tuple(float(v) for v in look_at)
        camera.up = tuple(float(v) for v in up)

    # ------------------------------------------------------------------ buttons

    def _on_solve(self, *_args: Any) -> None:
        from gscompress.pipeline.share.solve import solve_share

        budget = Budget.parse(f"{int(self.budget.value)}kB")
        self._say(f"solving for {budget} (rendering candidates)...")
        try:
            best, weighed, record = solve_share(
                self.source.path,
                budget,
                self._share_options(),
                fixed=("fold",),
                seq=self.options.seq,
                recording=self.options.recording,
            )  # # (the viewer's shares fold, as gsc share's do by default)
        except GscError as exc:
            self._say(f"**{exc}**")
            return
        rows = "\n".join(
            f"| {cuts.codec_label(c.codec, c.sums)} | {c.count:,} | {c.file_bytes:,} | "
            f"{c.psnr:.2f} |"
            for c in weighed
        )
        self._say(
            f"Solver (against the {record['against']}, {record['views']} views): "
            f"**{cuts.codec_label(best.codec, best.sums)}**\n\n"
            f"| codec | Gaussians | bytes | PSNR |\n|---|---|---|---|\n{rows}"
        )
        self.selection.value = SELECTIONS[1]
        self.codec.value, self.sums.value = best.codec, best.sums
        self._on_codec()

    def _on_write(self, *_args: Any) -> None:
        src, seed, strategy = self.source.path, self.options.seed, self.strategy.value
        try:
            if self.snapshot != self.source.snapshot_count - 1:
                raise OptionError("prune and share cut the map, the last snapshot: show it first")
            out = self.options.out_dir
            if self.selection.value == SELECTIONS[0]:
                keep = float(self.keep.value)
                suffix = ".mcap" if self.source.is_log else ".ply"
                dst = out / f"{src.stem}_keep{keep:g}_{strategy}{suffix}"
                result = cuts.write_prune(
                    src, self._source_pair(), self.source.is_log, dst, keep, strategy, seed
                )
            else:
                budget = Budget.parse(f"{int(self.budget.value)}kB")
                how = self._share_options()
                nosums = "" if how.sums else "_nosums"
                dst = out / f"{src.stem}_share{budget}_{how.codec}{nosums}.mcap"
                result = cuts.write_share(src, self._source_pair(), dst, budget, how)
        except (GscError, OSError) as exc:
            self._say(f"**not written: {exc}**")
            return
        self._say(f"wrote `{result['output']}`")
