"""`gsc view`: what the viewer draws (colours, covariances, frustums), the prune and share it
previews against the commands' own files, and the page itself in headless Chromium."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from gscompress.camera import Intrinsics, make_transform, quat_to_rotmat, rotmat_to_quat
from gscompress.gaussians import SH_C0, GaussianMap, random_map
from gscompress.io.mcap_log import LogMetadata, LogReader, LogWriter, read_map
from gscompress.io.ply import write_ply
from gscompress.ops.budget import Budget
from gscompress.ops.fold import fold
from gscompress.pipeline.share import share_log
from gscompress.pipeline.share.options import ShareOptions
from gscompress.selection import select_top
from gscompress.view import cuts, scene
from gscompress.view.source import MapSource
from gscompress_cli.main import cli

FRAMES = 6
KEYFRAMES = (0, 2, 4)


def camera_path(frames: int = FRAMES, drift: float = 0.0) -> list[np.ndarray]:
    """Camera-to-world poses stepping along x and turning a little, `drift` m off in y."""
    poses = []
    for i in range(frames):
        angle = 0.05 * i
        R = quat_to_rotmat(np.array([np.cos(angle / 2), 0.0, np.sin(angle / 2), 0.0]))
        poses.append(make_transform(R, np.array([0.1 * i, drift * i, -3.0])))
    return poses


def room_corner(n: int = 300, seed: int = 0) -> GaussianMap:
    """A scored, anisotropic map of `n` Gaussians on a back wall, a floor and a side wall in
    front of `camera_path`'s cameras (something a screenshot shows as a scene)."""
    rng = np.random.default_rng(seed)
    g = random_map(n, seed=seed, isotropic=False)
    u, v = rng.uniform(0.0, 1.0, (2, n))
    face = np.arange(n) % 3
    means = np.where(
        (face == 0)[:, None],
        np.stack([3 * u - 1.5, 2 * v - 1.0, np.zeros(n)], 1),  # back wall
        np.where(
            (face == 1)[:, None],
            np.stack([3 * u - 1.5, np.ones(n), -1.5 * v], 1),  # floor (+y is down)
            np.stack([np.full(n, -1.5), 2 * v - 1.0, -1.5 * u], 1),  # side wall
        ),
    )
    palette = np.array([[0.25, 0.45, 0.85], [0.85, 0.55, 0.25], [0.35, 0.75, 0.4]])
    rgb = np.clip(palette[face] * (0.7 + 0.5 * u)[:, None], 0.0, 1.0)
    return replace(
        g,
        means=means,
        log_scales=np.log(rng.uniform(0.05, 0.12, (n, 3))),
        opacity_logits=rng.uniform(1.5, 4.0, n),
        sh_dc=(rgb - 0.5) / SH_C0,
    )


def write_tiny_log(path: Path, n: int = 300, seed: int = 0, stats: bool = True) -> GaussianMap:
    """A log of a `n`-Gaussian map (`room_corner`) with an earlier snapshot of its first 200,
    estimated and ground-truth poses, a camera and (if `stats`) keyframe marks."""
    gaussians = room_corner(n, seed)
    with LogWriter(path, LogMetadata(command="test")) as out:
        out.write_calibration(Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24), 0)
        for i, (est, gt) in enumerate(zip(camera_path(drift=0.02), camera_path(), strict=True)):
            t = (i + 1) * 100_000_000
            out.write_pose(est, t)
            out.write_pose(gt, t, ground_truth=True)
            if stats:
                record = {"frame": i, "gaussians": n, "keyframe": i in KEYFRAMES}
                out.write_stats(record, t)
        out.write_gaussians(gaussians.select(slice(0, 200)), 300_000_000)
        out.write_gaussians(gaussians, FRAMES * 100_000_000)
    return gaussians


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("view") / "tiny.mcap"
    write_tiny_log(path)
    return path


# ---------------------------------------------------------------------- what is drawn


def test_covariances_are_rotated_squared_scales() -> None:
    g = random_map(50, seed=3, isotropic=False)
    cov = g.covariances().astype(np.float32)
    R = quat_to_rotmat(g.quats)
    for i in (0, 17, 49):
        expected = R[i] @ np.diag(np.exp(2.0 * g.log_scales[i].astype(np.float64))) @ R[i].T
        np.testing.assert_allclose(cov[i], expected, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), rtol=1e-6, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov.astype(np.float64)) > 0)


def test_isotropic_covariance_is_diagonal() -> None:
    g = random_map(20, seed=4, isotropic=True)
    cov = g.covariances().astype(np.float32)
    variances = np.exp(2.0 * g.log_scales[:, 0])
    np.testing.assert_allclose(cov, variances[:, None, None] * np.eye(3), rtol=1e-5, atol=1e-9)


def test_importance_colours_follow_a_log_scale() -> None:
    scores = np.array([0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0])
    scale = scene.LogScale.of(np.logspace(-4, 0, 101))
    unit = scale.unit(scores)
    assert unit[0] == 0.0  # an unscored Gaussian takes the lowest colour
    assert unit[1] == 0.0 and unit[-1] == 1.0  # beyond the 1st and 99th percentiles: clipped
    assert np.all(np.diff(unit[1:]) > 0)  # each decade brighter...
    np.testing.assert_allclose(np.diff(unit[2:5]), np.diff(unit[2:5])[0], rtol=1e-6)  # evenly
    colours = scene.unit_colors(unit)
    lightness = colours @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    assert np.all(np.diff(lightness[1:]) > 0)  # perceptual: lightness rises with the score
    legend = scene.legend_image(64, 5)
    assert legend.shape == (5, 64, 3) and legend.dtype == np.uint8
    np.testing.assert_array_equal(legend[0, 0], (scene.unit_colors(np.zeros(1))[0] * 255).round())


def test_kept_and_dropped_colours_and_hidden_splats() -> None:
    g = random_map(10, seed=1)
    kept = np.arange(10) < 4
    colours = scene.splat_colours(g, "kept / dropped", kept)
    np.testing.assert_array_equal(colours[:4], np.tile(scene.KEPT_RGB, (4, 1)))
    np.testing.assert_array_equal(colours[4:], np.tile(scene.DROPPED_RGB, (6, 1)))
    np.testing.assert_array_equal(scene.splat_colours(g, "rgb", kept), g.colors())
    hidden = scene.splat_opacities(g, kept, hide_dropped=True)
    assert hidden.shape == (10, 1)
    np.testing.assert_array_equal(hidden[4:], 0.0)
    np.testing.assert_array_equal(hidden[:4, 0], g.opacities()[:4])
    np.testing.assert_array_equal(scene.splat_opacities(g, kept, False)[:, 0], g.opacities())
    with pytest.raises(ValueError, match="unknown colour mode"):
        scene.splat_colours(g, "depth", kept)


def test_rgba_words_pack_like_the_splat_buffer() -> None:
    rgbs = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]], np.float32)
    opacities = np.array([[1.0], [0.2]], np.float32)
    words = scene.rgba_words(rgbs, opacities)
    assert words.dtype == np.uint32 and words.shape == (2,)
    bytes_ = words.view(np.uint8).reshape(2, 4)
    np.testing.assert_array_equal(bytes_, [[255, 0, 127, 255], [0, 255, 0, 51]])
    viser = pytest.importorskip("viser")  # the same bytes viser packs itself
    server = viser.ViserServer(port=0, verbose=False)
    try:
        handle = server.scene.add_gaussian_splats(
            "/x",
            centers=np.zeros((2, 3)),
            covariances=np.tile(np.eye(3), (2, 1, 1)) * 0.01,
            rgbs=rgbs,
            opacities=opacities,
        )
        np.testing.assert_array_equal(handle.buffer[:, 7], words)
    finally:
        server.stop()


def test_frustum_poses_round_trip() -> None:
    poses = np.array(camera_path())
    wxyz, positions = scene.frustum_poses(poses)
    np.testing.assert_allclose(quat_to_rotmat(wxyz), poses[:, :3, :3], atol=1e-12)
    np.testing.assert_array_equal(positions, poses[:, :3, 3])
    segments = scene.trajectory_segments(poses)
    assert segments.shape == (FRAMES - 1, 2, 3)
    np.testing.assert_allclose(segments[2, 1], poses[3, :3, 3], rtol=1e-6)


# ---------------------------------------------------------------------- what is read


def test_source_reads_snapshots_poses_and_keyframes(tiny_log: Path) -> None:
    source = MapSource.open(tiny_log)
    assert source.is_log and source.snapshot_count == 2
    assert len(source.snapshot()) == 300 and len(source.snapshot(0)) == 200
    assert source.poses.shape == source.poses_gt.shape == (FRAMES, 4, 4)
    assert source.poses[-1, 1, 3] == pytest.approx(0.02 * (FRAMES - 1))
    assert source.keyframes() == list(KEYFRAMES)
    truth = source.keyframe_truth(source.keyframes())
    np.testing.assert_allclose(truth, np.array(camera_path())[list(KEYFRAMES)], atol=1e-12)
    assert source.intrinsics is not None and source.intrinsics.width == 32


def test_source_reads_a_map_file(tmp_path: Path) -> None:
    g = random_map(40, seed=2)
    write_ply(g, tmp_path / "m.ply")
    source = MapSource.open(tmp_path / "m.ply")
    assert not source.is_log and source.snapshot_count == 1
    assert source.snapshot().equals(read_map_file_of(tmp_path / "m.ply"))
    assert len(source.poses) == 0 and source.keyframes() == []


def read_map_file_of(path: Path) -> GaussianMap:
    from gscompress.io.map_files import read_map_file

    return read_map_file(path)


# ---------------------------------------------------------------------- the previews


@pytest.mark.parametrize(("keep", "by"), [(0.3, "pwas"), (0.55, "opacity"), (1.0, "alpha-t")])
def test_prune_preview_is_what_prune_keeps(tiny_log: Path, keep: float, by: str) -> None:
    g = read_map(tiny_log)
    kept = cuts.kept_by_prune(g, keep, by, seed=0)
    _pruned, index = select_top(g, keep, by)
    assert kept.sum() == len(index) == round(keep * 300)
    np.testing.assert_array_equal(np.flatnonzero(kept), index)


def test_prune_button_writes_what_prune_writes(tiny_log: Path, tmp_path: Path) -> None:
    source = MapSource.open(tiny_log)
    pair = (source.snapshot(), source.metadata)
    result = cuts.write_prune(tiny_log, pair, True, tmp_path / "p.mcap", 0.4, "pwas", 0)
    assert result["kept"] == 120
    written = read_map(tmp_path / "p.mcap")
    _, index = select_top(pair[0], 0.4, "pwas")
    expected = fold(pair[0], index)  # (gsc prune folds by default)
    assert written.equals(expected)
    with LogReader(tmp_path / "p.mcap") as reader:
        assert reader.metadata.provenance[-1]["operation"]["keep"] == 0.4
        assert reader.metadata.command.startswith("gsc prune tiny.mcap --keep 0.4")


def test_prune_button_on_a_map_file_writes_a_map_file(tmp_path: Path) -> None:
    g = random_map(50, seed=5)
    write_ply(g, tmp_path / "m.ply")
    source = MapSource.open(tmp_path / "m.ply")
    pair = (source.snapshot(), source.metadata)
    cuts.write_prune(tmp_path / "m.ply", pair, False, tmp_path / "k.ply", 0.2, "opacity", 0)
    written = read_map_file_of(tmp_path / "k.ply")
    assert len(written) == 10
    assert np.array_equal(np.sort(written.ids), np.sort(select_top(g, 0.2, "opacity")[0].ids))


@pytest.mark.parametrize(("codec", "sums"), [("compact", True), ("compact", False), ("fp16", True)])
def test_share_preview_is_the_file_share_writes(
    tiny_log: Path, tmp_path: Path, codec: str, sums: bool
) -> None:
    source = MapSource.open(tiny_log)
    pair = (source.snapshot(), source.metadata)
    budget = Budget.parse("4kB")
    preview = cuts.preview_share(
        tiny_log, pair, budget, ShareOptions(strategy="pwas", codec=codec, sums=sums, seed=0)
    )
    assert 0 < preview.count < 300
    assert preview.file_bytes <= 4000
    dst = tmp_path / f"s_{codec}_{sums}.mcap"
    result = cuts.write_share(
        tiny_log, pair, dst, budget, ShareOptions(strategy="pwas", codec=codec, sums=sums, seed=0)
    )
    assert result["selected"] == preview.count
    assert dst.stat().st_size == preview.file_bytes  # the bytes shown are the bytes written
    shared = read_map(dst)
    if codec == "compact":  # (sent without ids: each written Gaussian is a previewed one)
        gaps = np.linalg.norm(shared.means[:, None] - preview.shared.means[None], axis=2)
        nearest = gaps.argmin(axis=1)
        assert len(set(nearest.tolist())) == len(shared) == preview.count
        assert gaps.min(axis=1).max() < 1e-3  # within the position grid's step
    else:
        np.testing.assert_array_equal(np.sort(shared.ids), np.sort(pair[0].ids[preview.kept]))
    # the sizes in the other codecs are those files of the same Gaussians
    assert set(preview.sizes) == {"compact", "compact, no sums", "fp16", "fp32"}
    assert preview.sizes["compact, no sums"] < preview.sizes["compact"] < preview.sizes["fp16"]
    assert preview.sizes["fp16"] < preview.sizes["fp32"]
    assert preview.sizes[cuts.codec_label(codec, sums)] == preview.file_bytes


def test_share_preview_matches_the_share_command(tiny_log: Path, tmp_path: Path) -> None:
    source = MapSource.open(tiny_log)
    preview = cuts.preview_share(
        tiny_log,
        (source.snapshot(), source.metadata),
        Budget.parse("3kB"),
        ShareOptions(strategy="opacity", codec="compact", sums=True, seed=0),
    )
    # the command line recorded in the share is part of its bytes: the preview records the
    # command it stands for, so `gsc share` run as that command sends the same file
    opacity = ShareOptions(strategy="opacity", codec="compact", sums=True, seed=0)
    command = cuts.share_command(tiny_log, Budget.parse("3kB"), opacity)
    assert command == "gsc share tiny.mcap --budget 3kB --strategy opacity --codec compact --seed 0"
    result = share_log(
        tiny_log, tmp_path / "cmd.mcap", "3kB", ShareOptions(strategy="opacity"), command=command
    )
    assert result["selected"] == preview.count
    assert result["file_bytes"] == preview.file_bytes


def test_share_of_a_map_file(tmp_path: Path) -> None:
    g = random_map(120, seed=6)
    write_ply(g, tmp_path / "m.ply")
    source = MapSource.open(tmp_path / "m.ply")
    pair = (source.snapshot(), source.metadata)
    budget = Budget.parse("3kB")
    how = ShareOptions(strategy="pwas", codec="compact", sums=False, seed=0)
    preview = cuts.preview_share(tmp_path / "m.ply", pair, budget, how)
    cuts.write_share(tmp_path / "m.ply", pair, tmp_path / "s.mcap", budget, how)
    assert (tmp_path / "s.mcap").stat().st_size == preview.file_bytes <= 3000
    assert 0 < preview.count < 120
    assert len(read_map(tmp_path / "s.mcap")) == preview.count


# ---------------------------------------------------------------------- the command


def test_view_help_and_bad_input(tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(cli, ["view", "--help"])
    assert result.exit_code == 0 and "--compare" in result.output and "--port" in result.output
    result = runner.invoke(cli, ["view", str(tmp_path / "missing.mcap")])
    assert result.exit_code == 2 and "does not exist" in result.output
    (tmp_path / "bad.mcap").write_bytes(b"not an mcap file at all")
    pytest.importorskip("viser")
    result = runner.invoke(cli, ["view", str(tmp_path / "bad.mcap"), "--port", "0"])
    assert result.exit_code == 1 and "bad.mcap" in result.output
    assert "Traceback" not in result.output


def test_view_serves_until_stopped(tiny_log: Path, terminated: Callable[..., Any]) -> None:
    pytest.importorskip("viser")
    gsc = str(Path(sys.executable).parent / "gsc")
    code, stderr = terminated(
        [gsc, "view", str(tiny_log), "--port", "0"],
        lambda text: "gsc view: http://127.0.0.1:" in text,
    )
    port = int(stderr.split("gsc view: http://127.0.0.1:")[1].split()[0])
    assert port > 0 and code == 0  # stopped cleanly: nothing to write, nothing interrupted
    assert "Traceback" not in stderr


def test_view_without_viser_names_the_extra(
    tiny_log: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import builtins

    real_import = builtins.__import__

    def no_viser(name: str, *args: object, **kwargs: object) -> object:
        if name == "viser" or name.startswith("viser."):
            raise ImportError("No module named 'viser'")
        return real_import(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(builtins, "__import__", no_viser)
    result = CliRunner().invoke(cli, ["view", str(tiny_log), "--port", "0"])
    assert result.exit_code == 2
    assert "pip install 'gscompress[view]'" in result.output


# ---------------------------------------------------------------------- the page


VISER_SPLAT_WARNING = "THREE.BufferGeometry.computeBoundingSphere(): Computed radius is NaN"
"""What three.js logs of viser's own splat mesh (its quad's "position" attribute has two
components; three.js reads a third), with any splats at all, this map's or not."""


def need_browser() -> Any:
    """gscompress.view.browser, or a skip saying why the page cannot be opened (a failure
    where GSC_REQUIRE_BROWSER is set: CI installs Chromium and viser)."""
    from gscompress.view import browser

    why = browser.missing()
    if why is not None:
        if os.environ.get("GSC_REQUIRE_BROWSER"):
            pytest.fail(f"GSC_REQUIRE_BROWSER is set, but {why}")
        pytest.skip(f"no browser test: {why}")
    return browser


@pytest.mark.slow
@pytest.mark.browser
def test_page_loads_draws_and_follows_the_keep_slider(tiny_log: Path, tmp_path: Path) -> None:
    browser = need_browser()
    from gscompress.view import MapViewer, ViewOptions

    viewer = MapViewer(tiny_log, ViewOptions(port=0, out_dir=tmp_path))
    try:
        url = f"http://127.0.0.1:{viewer.port}"
        with browser.open_page(url, 1024, 600) as (page, errors):
            browser.wait_for_text(page, "Kept 300 of 300 Gaussians")
            assert page.title() == f"{tiny_log.name} - gsc view"  # (not viser's "Viser")
            page.wait_for_timeout(1500)  # (the splats sorted and drawn)
            png = page.screenshot()
            colours, spread = browser.canvas_spread(png)
            assert colours > 1000 and spread > 10.0, "the page is blank"
            updates = viewer.updates
            browser.set_slider(page, "Keep ratio", 0.5)
            browser.wait_for_text(page, "Kept 150 of 300 Gaussians")
            assert viewer.updates == updates + 1  # the splats were redrawn once
            assert int(viewer.splats.opacities.astype(bool).sum()) <= 150  # the rest hidden
            viewer.colour.value = "importance"  # (as a click in its menu sets it)
            browser.wait_for_text(page, "log10 PWAS score")  # the legend
            browser.dismiss_notices(page)
            page.wait_for_timeout(1000)
            screenshot = os.environ.get("GSC_VIEW_SCREENSHOT")  # (`make screenshot`)
            png = page.screenshot(path=screenshot)
            assert browser.canvas_spread(png)[0] > 1000
            own = [e for e in errors if VISER_SPLAT_WARNING not in e]
            assert own == [], f"console errors: {own}"
    finally:
        viewer.close()


def test_the_server_draws_what_gsc_renders_at_the_page_camera() -> None:
    """The page's camera (OpenCV frame, vertical field of view) gives the renderer's own
    picture of the visible layers, in their colours, hidden Gaussians left out."""
    from gscompress.ops.evaluate import render_view
    from gscompress.ops.score import activated_tensors
    from gscompress.view.server_render import Layer, ServerRenderer, page_intrinsics, page_pose

    g = room_corner()
    T = camera_path()[2]
    wxyz = rotmat_to_quat(T[:3, :3][None])[0]
    camera = (tuple(wxyz), tuple(T[:3, 3]), 0.9, 96, 64)
    K = page_intrinsics(0.9, 96, 64)
    np.testing.assert_allclose(page_pose(wxyz, T[:3, 3]), T, atol=1e-12)
    assert (K.width, K.height, K.cx, K.cy) == (96, 64, 48.0, 32.0)
    assert K.fy == pytest.approx(32 / np.tan(0.45))  # half the height over tan(fov / 2)

    renderer = ServerRenderer(None, device="cpu")
    assert renderer.draw(camera, 1.0).max() == 0  # nothing to draw yet: black
    renderer.set_layer("a", Layer(g, g.colors(), g.opacities()[:, None]))
    picture = renderer.draw(camera, 1.0)
    expected, _ = render_view(activated_tensors(g), T, K)
    assert picture is not None and picture.shape == (64, 96, 3)
    np.testing.assert_array_equal(picture, np.round(expected * 255).astype(np.uint8))
    assert renderer.draw(camera, 0.5).shape == (32, 48, 3)  # while the camera moves

    hidden = np.arange(len(g)) % 2 == 0
    opacities = np.where(hidden, 0.0, g.opacities())[:, None]
    red = np.tile([1.0, 0.0, 0.0], (len(g), 1))
    renderer.set_layer("a", Layer(g, red, opacities))
    params = activated_tensors(g.select(np.flatnonzero(~hidden)))
    params["colors"] = params["colors"].new_tensor(red[~hidden])
    kept, _ = render_view(params, T, K)
    shown = renderer.draw(camera, 1.0)
    assert shown[..., 1:].max() == 0 and shown[..., 0].max() > 100  # red only
    np.testing.assert_array_equal(shown, np.round(kept * 255).astype(np.uint8))  # the kept only
    renderer.show("a", False)
    assert renderer.draw(camera, 1.0).max() == 0


def test_moving_frames_shrink_when_slow_and_grow_when_fast_within_their_range() -> None:
    """While the camera moves, each frame's time sets the next one's size: a frame that took
    four times `MOTION_FRAME_S` halves the side, a quick one doubles it, within the range (a
    time that is no time keeps the scale)."""
    from gscompress.view import server_render as sr

    low, high = sr.MOTION_SCALE_RANGE
    target = sr.MOTION_FRAME_S
    assert sr.next_motion_scale(0.8, 4 * target) == pytest.approx(0.4)
    assert sr.next_motion_scale(0.4, target / 4) == pytest.approx(0.8)
    assert sr.next_motion_scale(0.5, target) == pytest.approx(0.5)
    assert sr.next_motion_scale(0.5, 100 * target) == low
    assert sr.next_motion_scale(0.9, target / 100) == high
    assert sr.next_motion_scale(0.5, 0.0) == sr.next_motion_scale(0.5, float("nan")) == 0.5
    # settles: a frame's time taken as proportional to its pixels, the scale reaches the one
    # whose frames take MOTION_FRAME_S
    scale, seconds_at_full = sr.MOTION_SCALE, 9 * target  # full size takes 9 frames' time
    for _ in range(5):
        scale = sr.next_motion_scale(scale, seconds_at_full * scale**2)
    assert scale == pytest.approx(1 / 3, rel=1e-3)


def test_the_server_draws_no_more_than_its_pixel_cap_and_refuses_no_camera() -> None:
    """A page's camera messages are input: a huge canvas is drawn at `MAX_PIXELS`, and a
    message that is no camera (NaN, a zero rotation, no size, wrong lengths) draws nothing."""
    from gscompress.view import server_render as sr

    K = sr.page_intrinsics(0.9, 100_000, 50_000)
    assert K.width * K.height <= sr.MAX_PIXELS and K.width / K.height == pytest.approx(2, 1e-3)
    assert sr.page_intrinsics(0.0, 64, 48).fy == pytest.approx(24 / np.tan(sr.FOV_RANGE[0] / 2))
    g = room_corner()
    renderer = sr.ServerRenderer(None, device="cpu")
    renderer.set_layer("a", sr.Layer(g, g.colors(), g.opacities()[:, None]))
    identity, origin = (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -3.0)
    assert renderer.draw((identity, origin, 0.9, 64, 48), 1.0) is not None
    for camera in (
        ((float("nan"), 0.0, 0.0, 0.0), origin, 0.9, 64, 48),
        ((0.0, 0.0, 0.0, 0.0), origin, 0.9, 64, 48),
        (identity, (0.0, float("inf"), 0.0), 0.9, 64, 48),
        (identity, origin, 0.9, 0, 48),
        (identity[:3], origin, 0.9, 64, 48),
        (identity, origin, None, 64, 48),
    ):
        assert renderer.draw(camera, 1.0) is None, camera


@pytest.mark.slow
@pytest.mark.browser
def test_page_shows_the_server_s_frames_and_follows_the_keep_slider(
    tiny_log: Path, tmp_path: Path
) -> None:
    """`gsc view --render server`: the page shows the server's pictures, taken at its own
    camera, and a slider's change is drawn again."""
    browser = need_browser()
    from gscompress.view import MapViewer, ViewOptions
    from gscompress.view.server_render import page_intrinsics, page_pose

    viewer = MapViewer(tiny_log, ViewOptions(port=0, out_dir=tmp_path, render="server"))
    renderer = viewer.renderer
    assert renderer is not None and viewer.splats is None  # no splats sent to the page

    def full_frame_sent(after: int, timeout_s: float = 60.0) -> None:
        camera = next(iter(viewer.server.get_clients().values())).camera
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if renderer.frames_sent > after and renderer.last_frame[:2] == (
                camera.image_width,
                camera.image_height,
            ):
                return
            time.sleep(0.05)
        raise AssertionError(
            f"no full-size frame: {renderer.frames_sent} sent, last {renderer.last_frame}"
        )

    try:
        url = f"http://127.0.0.1:{viewer.port}"
        with browser.open_page(url, 1024, 600) as (page, errors):
            browser.wait_for_text(page, "Kept 300 of 300 Gaussians")
            full_frame_sent(0)
            page.wait_for_timeout(500)  # (the image decoded and shown)
            colours, spread = browser.canvas_spread(page.screenshot())
            assert colours > 1000 and spread > 10.0, "the page is blank"
            camera = next(iter(viewer.server.get_clients().values())).camera
            K = page_intrinsics(camera.fov, camera.image_width, camera.image_height)
            target = np.linalg.inv(page_pose(camera.wxyz, camera.position)) @ [*camera.look_at, 1]
            pixel = K.fx * target[0] / target[2] + K.cx, K.fy * target[1] / target[2] + K.cy
            assert target[2] > 0 and np.allclose(pixel, (K.cx, K.cy), atol=1.0)  # looked at
            sent = renderer.frames_sent
            browser.set_slider(page, "Keep ratio", 0.5)
            browser.wait_for_text(page, "Kept 150 of 300 Gaussians")
            full_frame_sent(sent)
            inputs = renderer._render_inputs()
            assert inputs is not None and int((inputs["opacities"] > 0).sum()) <= 150
            own = [e for e in errors if VISER_SPLAT_WARNING not in e]
            assert own == [], f"console errors: {own}"
    finally:
        viewer.close()


def test_viewer_follows_its_controls(tiny_log: Path, tmp_path: Path) -> None:
    """The server side without a browser: snapshots, the share preview, B with the share, the
    write button."""
    pytest.importorskip("viser")
    from gscompress.view import MapViewer, ViewOptions
    from gscompress.view.app import COMPARE_MODES, SELECTIONS

    other = tmp_path / "b.mcap"
    write_tiny_log(other, n=120, seed=9)
    viewer = MapViewer(tiny_log, ViewOptions(port=0, compare=other, out_dir=tmp_path))
    try:
        assert len(viewer.splats.centers) == 300
        viewer.frustums_drawn.join()  # (drawn from a thread: the SLAM config may load torch)
        assert [len(viewer._trajectory_nodes[k]) for k in ("frustums", "gt_frustums")] == [3, 3]
        viewer.show_truth.value = False
        viewer._on_trajectory_visibility()
        assert not any(node.visible for node in viewer._trajectory_nodes["gt_frustums"])
        assert all(node.visible for node in viewer._trajectory_nodes["frustums"])
        viewer.snapshot_slider.value = 0
        viewer._on_snapshot()
        viewer._redraw()
        assert len(viewer.splats.centers) == 200 and "Snapshot 1 of 2" in viewer.map_info.content
        viewer._on_write()
        assert "show it first" in viewer.status.content  # only the last snapshot is cut
        viewer.snapshot_slider.value = 1
        viewer._on_snapshot()
        viewer.selection.value = SELECTIONS[1]
        viewer.budget.value = 5
        viewer._redraw()
        share = viewer._share
        assert share is not None and 0 < share.count < 300
        assert f"Sent {share.count:,} of 300" in viewer.counts.content
        hidden = viewer.splats.opacities[:, 0] == 0
        np.testing.assert_array_equal(~hidden, share.kept)  # only the sent ones drawn
        viewer.compare.value = COMPARE_MODES[3]
        viewer._redraw()
        assert not viewer.splats.visible and viewer.splats_b.visible
        assert len(viewer._drawn["share_node"].centers) == share.count
        viewer._on_write()
        written = tmp_path / "tiny_share5kB_compact.mcap"
        assert "wrote" in viewer.status.content and written.exists()
        assert written.stat().st_size == share.file_bytes
    finally:
        viewer.close()


def test_server_layers_follow_the_compare_modes(tiny_log: Path, tmp_path: Path) -> None:
    pytest.importorskip("viser")
    from gscompress.view import MapViewer, ViewOptions
    from gscompress.view.app import COMPARE_MODES, SELECTIONS

    other = tmp_path / "b.mcap"
    write_tiny_log(other, n=120, seed=9)
    viewer = MapViewer(tiny_log, ViewOptions(port=0, compare=other, render="server"))
    try:
        assert viewer.renderer is not None
        layers = viewer.renderer._layers

        def shown() -> dict[str, int]:
            return {k: len(v.gaussians) for k, v in layers.items() if v.visible}

        assert shown() == {"map_a": 300}
        viewer.compare.value = COMPARE_MODES[2]
        viewer._redraw()
        assert shown() == {"map_a": 300, "map_b": 120} and layers["map_b"].offset[0] > 0
        viewer.selection.value = SELECTIONS[1]
        viewer.budget.value = 5
        viewer.compare.value = COMPARE_MODES[3]
        viewer._redraw()
        share = viewer._share
        assert share is not None
        assert shown() == {"map_b": 120, "share_on_b": share.count}
        assert layers["map_b"].offset == (0.0, 0.0, 0.0)
        viewer.compare.value = COMPARE_MODES[1]
        viewer._redraw()
        assert shown() == {"map_b": 120}
    finally:
        viewer.close()


def test_solver_button_picks_a_codec(tiny_log: Path) -> None:
    pytest.importorskip("viser")
    from gscompress.view import MapViewer, ViewOptions
    from gscompress.view.app import SELECTIONS

    viewer = MapViewer(tiny_log, ViewOptions(port=0))
    try:
        viewer.budget.value = 6
        viewer._on_solve()
        status = viewer.status.content
        assert "Solver (against the map renders" in status, status
        assert status.count("\n| ") == 1 + 4  # a header and the four candidates
        assert viewer.selection.value == SELECTIONS[1]
        chosen = status.split("**")[1]  # the best candidate, named in bold
        assert chosen == cuts.codec_label(viewer.codec.value, viewer.sums.value)
    finally:
        viewer.close()
