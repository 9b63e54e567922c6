"""The C++ kernels (projection, binning, compositing, SSIM) against the pure-torch oracle:
values, gradients, contribution."""

from __future__ import annotations

import os
import shutil
import time
import warnings
from pathlib import Path

import pytest
import torch
from test_render import (
    ARGS,
    INTR,
    _pose_function,
    assert_rel_close,
    loss_weights,
    make_scene,
    outputs_loss,
    run,
)

from gscompress import metrics
from gscompress.camera import Intrinsics
from gscompress.errors import InputError
from gscompress.render import RenderOutput, render, resolve_backend
from gscompress.render import cpu as cpu_backend
from gscompress.render.cpu import build as cpu_build
from gscompress.slam.config import preset
from gscompress.slam.losses import depth_edges, mapping_loss

INPUTS = (*ARGS, "T_cam_world")
TOL = {torch.float64: 1e-10, torch.float32: 1e-5}


@pytest.fixture(scope="module", autouse=True)
def extension():
    """Build (or load) the extension once for this module. Skip without a compiler; with one, a
    failed build fails the tests (the backend would fall back to torch and hide it)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ext = cpu_backend.load_extension()
    if ext is None:
        if shutil.which(os.environ.get("CXX", "c++")) is None:
            pytest.skip("no C++ compiler: the C++ render kernels cannot be built")
        why = "; ".join(str(w.message) for w in caught) or "see the first warning of this run"
        pytest.fail(f"the C++ render kernels failed to build: {why}")
    return ext


def _on_threads(n, fn):
    """fn() computed with torch (and the kernels) on n threads; the count is restored after."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(n)
        return fn()
    finally:
        torch.set_num_threads(before)


def _render_and_grads(scene, backend, **kw):
    scene = {k: v.detach().clone().requires_grad_(True) for k, v in scene.items()}
    out = run(scene, backend=backend, **kw)
    weights = loss_weights(scene["means"].dtype)
    grads = torch.autograd.grad(outputs_loss(out, weights), [scene[k] for k in INPUTS])
    return out, dict(zip(INPUTS, grads, strict=True))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(("seed", "n", "scale"), [(0, 300, 1.0), (1, 500, 2.0), (2, 200, 0.5)])
def test_cpu_equals_torch_values_and_gradients(dtype, seed, n, scale):
    scene = make_scene(n, seed=seed, dtype=dtype, scale=scale)
    bg = torch.tensor([0.7, 0.1, 0.4], dtype=dtype)
    ours, g_ours = _render_and_grads(scene, "cpu", want_contribution=True, background=bg)
    ref, g_ref = _render_and_grads(scene, "torch", want_contribution=True, background=bg)
    assert ours.backend == "cpu" and ref.backend == "torch"
    tol = TOL[dtype]
    for key in ("color", "depth", "depth_normalized", "silhouette", "contribution"):
        assert_rel_close(getattr(ours, key), getattr(ref, key), tol, key)
    assert torch.equal(ours.radii, ref.radii)
    for key in INPUTS:
        assert g_ref[key].abs().max() > 0, key
        assert_rel_close(g_ours[key], g_ref[key], tol, f"grad {key}")


def _compare_backends(scene, intr, tol):
    """Render `scene` at `intr` with the cpu and torch backends; values and gradients agree."""
    g = torch.Generator().manual_seed(16)
    dtype, shape = scene["means"].dtype, (intr.height, intr.width)
    weights = {
        key: torch.rand(*shape, *extra, generator=g, dtype=torch.float64).to(dtype)
        for key, extra in (("color", (3,)), ("depth", ()), ("silhouette", ()))
    }
    results = []
    for backend in ("cpu", "torch"):
        leaves = {k: v.detach().clone().requires_grad_(True) for k, v in scene.items()}
        out = render(
            *(leaves[k] for k in ARGS),
            intr,
            leaves["T_cam_world"],
            backend=backend,
            want_contribution=True,
        )
        assert out.backend == backend
        loss = outputs_loss(out, weights)
        results.append((out, torch.autograd.grad(loss, [leaves[k] for k in INPUTS])))
    (ours, g_ours), (ref, g_ref) = results
    for key in ("color", "depth", "silhouette", "contribution"):
        assert_rel_close(getattr(ours, key), getattr(ref, key), tol, key)
    assert torch.equal(ours.radii, ref.radii)
    for key, a, b in zip(INPUTS, g_ours, g_ref, strict=True):
        assert b.abs().max() > 0, key
        assert_rel_close(a, b, tol, f"grad {key}")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_partial_tiles_equal_torch(dtype):
    """37x21: the last tile column is 5 pixels wide and the last row 5 high, so the kernels'
    lane masks, row segments and write-back of partly filled tiles are compared too."""
    intr = Intrinsics(fx=32.0, fy=30.0, cx=18.0, cy=10.0, width=37, height=21)
    _compare_backends(make_scene(400, seed=14, dtype=dtype), intr, TOL[dtype])


@pytest.mark.slow
def test_portable_build_equals_torch(monkeypatch, tmp_path):
    """The build without -march=native (any CPU that cannot be identified, or not x86-64) uses
    16-byte vectors: 4 float lanes, so a Gaussian spans up to 4 segments of a tile row (8 for
    double), and no FMA. Built afresh into a temporary cache, it renders as the torch oracle
    does, and its SSIM equals torch's."""
    monkeypatch.setattr(cpu_build, "_cpu_signature", lambda: None)
    monkeypatch.setenv("GSCOMPRESS_CACHE_DIR", str(tmp_path))
    assert cpu_build._build_flags() == (list(cpu_build._CFLAGS), "generic")
    cpu_backend.load_extension.cache_clear()
    try:
        assert cpu_backend.load_extension() is not None
        assert any(p.name.endswith(".so") for p in tmp_path.rglob("*"))  # built here, afresh
        intr = Intrinsics(fx=32.0, fy=30.0, cx=18.0, cy=10.0, width=37, height=21)
        for dtype in (torch.float64, torch.float32):
            _compare_backends(make_scene(300, seed=15, dtype=dtype), intr, TOL[dtype])
            _compare_ssim(cpu_backend.load_extension(), (3, 23, 37), dtype)
    finally:
        cpu_backend.load_extension.cache_clear()


def test_march_override_picks_the_build_target(monkeypatch):
    """$GSCOMPRESS_MARCH: `generic` gives the portable flags, a named target its own -march and
    a key that does not depend on the CPU, `native` (or unset) the usual build; anything that
    is not a plain target name is refused before it reaches the compiler's command line."""
    monkeypatch.setattr(cpu_build, "_cpu_signature", lambda: "model name: X\nflags: avx2")
    monkeypatch.setattr(cpu_build.platform, "machine", lambda: "x86_64")
    native = ([*cpu_build._CFLAGS, "-march=native"], "model name: X\nflags: avx2")
    monkeypatch.delenv(cpu_backend.MARCH_ENV, raising=False)
    assert cpu_build._build_flags() == native
    for value, expected in [
        ("native", native),
        (" native ", native),
        ("", native),
        ("generic", (list(cpu_build._CFLAGS), "generic")),
        ("x86-64-v3", ([*cpu_build._CFLAGS, "-march=x86-64-v3"], "march=x86-64-v3")),
    ]:
        monkeypatch.setenv(cpu_backend.MARCH_ENV, value)
        assert cpu_build._build_flags() == expected, value
    for bad in ("x86-64 -O0", "-v3", "a;b", "$(x)"):
        monkeypatch.setenv(cpu_backend.MARCH_ENV, bad)
        with pytest.raises(InputError, match="GSCOMPRESS_MARCH"):
            cpu_build._build_flags()


def test_checkouts_of_the_same_sources_build_apart(tmp_path):
    """Two copies of the kernels' sources get different build directories (a shared one made
    each rebuild after the other), the same copy the same one, and an edit a new one."""
    copies = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        copies.append(tuple(Path(shutil.copy(s, tmp_path / name)) for s in cpu_build._SOURCES))

    def key(sources: tuple[Path, ...]) -> str:
        return cpu_build._cache_key(sources, ["-O3"], "generic", "c++")

    assert key(copies[0]) == key(copies[0]) != key(copies[1])
    before = key(copies[1])
    copies[1][0].write_text(copies[1][0].read_text() + "\n// edited\n")
    assert key(copies[1]) != before


def test_deep_scene_reaches_the_stopping_rule():
    scene = make_scene(600, seed=3, scale=3.0)
    scene["opacities"] = torch.full_like(scene["opacities"], 0.9)
    ours, g_ours = _render_and_grads(scene, "cpu")
    ref, g_ref = _render_and_grads(scene, "torch")
    assert (1 - ref.silhouette).min() < 2e-4  # saturated pixels exist
    assert_rel_close(ours.color, ref.color, 1e-10, "color")
    for key in INPUTS:
        assert_rel_close(g_ours[key], g_ref[key], 1e-10, f"grad {key}")


def test_contribution_does_not_change_other_outputs():
    scene = make_scene(300, seed=4)
    with_c = run(scene, backend="cpu", want_contribution=True)
    without = run(scene, backend="cpu")
    assert without.contribution is None
    assert torch.equal(with_c.color, without.color) and torch.equal(with_c.depth, without.depth)
    assert torch.isclose(with_c.contribution.sum(), with_c.silhouette.sum(), rtol=1e-12)


def test_results_do_not_depend_on_thread_count():
    """Per-Gaussian sums are reduced in list order, so threads change nothing, bit for bit."""
    scene = make_scene(300, seed=5)
    one, g_one = _on_threads(1, lambda: _render_and_grads(scene, "cpu", want_contribution=True))
    two, g_two = _on_threads(2, lambda: _render_and_grads(scene, "cpu", want_contribution=True))
    assert torch.equal(one.color, two.color)
    assert torch.equal(one.contribution, two.contribution)
    # direct kernel outputs, before any torch reduction (the pose's sum is the projection's)
    for key in ("opacities", "colors", "means", "quats", "scales", "T_cam_world"):
        assert torch.equal(g_one[key], g_two[key]), key


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpu_projection_equals_torch(extension, dtype):
    """The C++ projection alone against `project_gaussians`, on Gaussians behind the camera,
    nearer than `near`, far outside the view (the Jacobian's clamp bites) and degenerate ones:
    the same values bit for bit (same operations in the same order) and the same gradients of
    every input, the camera pose included."""
    from gscompress.render.cpu import project_cpu
    from gscompress.render.projection import project_gaussians

    scene = make_scene(400, seed=11, dtype=dtype)
    scene["means"][:40] *= 6.0  # well beyond the clamp limits of x/z, y/z
    scene["scales"][40:50, 1:] = 0.0  # flat: a positive definite 2D covariance only by eps2d
    names = ("means", "quats", "scales", "T_cam_world")
    g = torch.Generator()

    def weighted(proj):  # the same random weights on every call
        g.manual_seed(12)
        return sum(
            (x * torch.randn(x.shape, generator=g, dtype=torch.float64).to(dtype)).sum()
            for x in (proj.means2d, proj.conics, proj.depths)
        )

    results = []
    for project in (project_gaussians, lambda *a: project_cpu(extension, *a)):
        inputs = [scene[k].detach().clone().requires_grad_(True) for k in names]
        proj = project(*inputs, INTR, 0.1)
        results.append((proj, torch.autograd.grad(weighted(proj), inputs)))
    (ref, g_ref), (ours, g_ours) = results
    assert (ref.radii == 0).sum() > 40 and (ref.radii > 0).sum() > 100
    assert torch.equal(ours.radii, ref.radii)
    for key in ("means2d", "conics", "depths"):
        assert torch.equal(getattr(ours, key), getattr(ref, key)), key
    for key, a, b in zip(names, g_ours, g_ref, strict=True):
        assert b.abs().max() > 0, key
        assert_rel_close(a, b, TOL[dtype], f"grad {key}")
    # with only the pose needing a gradient (tracking) the kernel skips the per-Gaussian ones,
    # and the pose's comes out the same bit for bit
    pose = scene["T_cam_world"].detach().clone().requires_grad_(True)
    fixed = [scene[k].detach() for k in names[:3]]
    (g_pose,) = torch.autograd.grad(
        weighted(project_cpu(extension, *fixed, pose, INTR, 0.1)), [pose]
    )
    assert torch.equal(g_pose, g_ours[3])
    # and one Gaussian parameter alone still gets its gradient
    scales = scene["scales"].detach().clone().requires_grad_(True)
    proj = project_cpu(extension, *fixed[:2], scales, scene["T_cam_world"].detach(), INTR, 0.1)
    (g_scales,) = torch.autograd.grad(weighted(proj), [scales])
    assert torch.equal(g_scales, g_ours[2])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cpu_tile_bins_equal_torch(extension, dtype):
    """The C++ binning gives `bin_tiles`'s lists exactly, depth ties (by index) included."""
    from gscompress.render.cpu import bin_tiles_cpu
    from gscompress.render.projection import bin_tiles, project_gaussians

    scene = make_scene(2000, seed=13, dtype=dtype, scale=0.5)
    intr = Intrinsics(fx=70.0, fy=68.0, cx=49.5, cy=37.5, width=100, height=75)  # partial tiles
    means = scene["means"].clone()
    means[100:200] = means[:100]  # exact duplicates: equal depths in the same tiles
    proj = project_gaussians(
        means, scene["quats"], scene["scales"], scene["T_cam_world"], intr, 0.01
    )
    ref = bin_tiles(proj, intr.width, intr.height)
    ours = bin_tiles_cpu(extension, proj, intr.width, intr.height)
    assert (ref.tiles_x, ref.tiles_y) == (ours.tiles_x, ours.tiles_y) == (7, 5)
    assert len(ref.ids) > 2000
    assert torch.equal(ours.offsets, ref.offsets) and torch.equal(ours.ids, ref.ids)


def test_gradcheck_camera_pose_cpu():
    scene = {k: v.detach() for k, v in make_scene(40, seed=7).items()}
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(_pose_function(scene, "cpu"), (xi,), eps=1e-6, atol=1e-6)


def test_gradcheck_kernel_inputs():
    """The C++ backward alone, against finite differences of the C++ forward."""
    scene = {k: v.detach() for k, v in make_scene(30, seed=8, scale=2.0).items()}
    weights = loss_weights()

    def f(opacities, colors, means):
        res = run(dict(scene, opacities=opacities, colors=colors, means=means), backend="cpu")
        assert res.backend == "cpu"
        return torch.stack([(getattr(res, k) * w).sum() for k, w in weights.items()])

    args = tuple(scene[k].clone().requires_grad_(True) for k in ("opacities", "colors", "means"))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6)


def test_non_contiguous_inputs():
    scene = make_scene(200, seed=9)
    strided = {k: v.t().contiguous().t() if v.dim() == 2 else v for k, v in scene.items()}
    assert not strided["means"].is_contiguous()
    a, b = run(scene, backend="cpu"), run(strided, backend="cpu")
    assert torch.equal(a.color, b.color)


def test_falls_back_to_torch_without_a_compiler(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler-gsc")
    cpu_backend.load_extension.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler"):
            out = run(make_scene(50, seed=10), backend="cpu")
        assert out.backend == "torch"
        assert resolve_backend("cpu", torch.device("cpu")) == "torch"
    finally:
        cpu_backend.load_extension.cache_clear()


def test_a_lock_left_by_a_killed_build_is_cleared(tmp_path):
    import subprocess
    import sys

    stale = tmp_path / "lock"
    stale.write_text("")  # what torch leaves when a build is killed midway
    with cpu_build._build_lock(tmp_path):
        assert not stale.exists()
        # another process cannot enter while this one builds
        probe = (
            "import fcntl, sys; f = open(sys.argv[1], 'w')\n"
            "try: fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)\n"
            "except BlockingIOError: sys.exit(3)"
        )
        held = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "gsc.lock")])
        assert held.returncode == 3


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", [(15, 120, 160), (3, 11, 11), (4, 23, 37)])
def test_cpu_blur_equals_torch_values_and_gradients(extension, dtype, shape):
    """The SSIM filter's C++ kernel and its transpose against the grouped convolutions of
    `metrics.blur` and their autograd: at the SLAM loss's size, at the smallest image the window
    allows and at odd sizes; threads change nothing. The window is not symmetric here (SSIM's
    is), so that a flipped filter would show."""
    g = torch.Generator().manual_seed(sum(shape))
    x = torch.rand(shape, generator=g, dtype=dtype)
    weights = torch.rand((shape[0], shape[1] - 10, shape[2] - 10), generator=g, dtype=dtype)
    window = torch.rand(11, generator=g, dtype=torch.float64)
    xi = x.clone().requires_grad_(True)
    ref = metrics.blur(xi[None], window)[0]
    (g_ref,) = torch.autograd.grad((ref * weights).sum(), xi)
    k = window.to(dtype)
    ours = extension.blur_forward(x, k)
    g_ours = extension.blur_backward(weights, k, shape[1], shape[2])
    assert ours.shape == weights.shape and g_ours.shape == x.shape
    assert_rel_close(ours, ref, TOL[dtype], "blur")
    assert_rel_close(g_ours, g_ref, TOL[dtype], "blur gradient")
    assert torch.equal(_on_threads(1, lambda: extension.blur_forward(x, k)), ours)
    assert torch.equal(
        _on_threads(1, lambda: extension.blur_backward(weights, k, shape[1], shape[2])), g_ours
    )


def _compare_ssim(extension, shape: tuple[int, int, int], dtype: torch.dtype) -> None:
    """The fused C++ mean SSIM against `metrics.ssim_maps` and autograd (value and gradient with
    respect to the first image); the result does not depend on the thread count."""
    g = torch.Generator().manual_seed(7 + sum(shape))
    y = torch.rand(shape, generator=g, dtype=dtype)
    x = (0.7 * y + 0.3 * torch.rand(shape, generator=g, dtype=dtype)).requires_grad_(True)
    ref = metrics.ssim_maps(x[None], y[None])[0].mean()
    (g_ref,) = torch.autograd.grad(ref, x)
    assert 0.2 < float(ref.detach()) < 0.99  # neither trivial nor saturated

    def ours() -> tuple[torch.Tensor, torch.Tensor]:
        value = cpu_backend.ssim_mean_cpu(extension, x, y)
        return value, torch.autograd.grad(value * 1.5, x)[0]  # a gradient other than 1

    value, grad = ours()
    assert_rel_close(value, ref, TOL[dtype], "ssim")
    assert_rel_close(grad, 1.5 * g_ref, TOL[dtype], "ssim gradient")
    v1, g1 = _on_threads(1, ours)
    assert torch.equal(v1, value) and torch.equal(g1, grad)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", [(3, 120, 160), (3, 11, 11), (2, 23, 37)])
def test_cpu_ssim_equals_torch_values_and_gradients(extension, dtype, shape):
    """The mapping loss's SSIM kernel at the loss's size, the smallest size and odd sizes."""
    _compare_ssim(extension, shape, dtype)
    y = torch.rand(shape, dtype=dtype, requires_grad=True)
    with pytest.raises(ValueError, match="first image"):
        cpu_backend.ssim_mean_cpu(extension, torch.rand(shape, dtype=dtype), y)
    x = torch.rand(shape, dtype=dtype)
    y = y.detach()
    k = metrics.gaussian_window().to(dtype)
    _, filtered = extension.ssim_forward(x, y, k, 1e-4, 9e-4)
    one = torch.ones((), dtype=dtype)
    with pytest.raises(RuntimeError, match="same size"):  # the bound kernel checks its inputs
        extension.ssim_backward(x, y[:1].contiguous(), k, filtered, one, 1e-4, 9e-4)
    with pytest.raises(RuntimeError, match="filtered must be"):
        extension.ssim_backward(x, y, k, filtered[:3].contiguous(), one, 1e-4, 9e-4)


def test_mapping_loss_with_the_cpu_ssim_equals_torch(extension):
    """The SLAM mapping loss (whose SSIM is the fused C++ kernel on cpu renders) equals the
    all-torch loss, value and gradients, with its depth edges computed or passed in."""
    g = torch.Generator().manual_seed(3)
    color_gt, depth_gt = torch.rand(40, 48, 3, generator=g), torch.rand(40, 48, generator=g) + 1
    depth_gt[:5, :7] = 0.0  # some pixels without depth
    config = preset("cpu").mapping
    grads = {}
    for backend, edges in (
        ("cpu", None),
        ("cpu", depth_edges(depth_gt, config.illum_edge_sigma)),
        ("torch", None),
    ):
        color = torch.rand(40, 48, 3, generator=torch.Generator().manual_seed(4))
        color.requires_grad_(True)
        out = RenderOutput(
            color, depth_gt * 1.1, depth_gt, torch.ones(40, 48), None, backend, lambda: None
        )
        terms = mapping_loss(out, color_gt, depth_gt, config, edges)
        key = backend if edges is None else "cpu, edges given"
        grads[key] = (terms.total.detach(), torch.autograd.grad(terms.total, color)[0])
    assert config.ssim_weight > 0 and config.illum_tau > 0
    assert torch.equal(grads["cpu"][0], grads["cpu, edges given"][0])
    assert torch.equal(grads["cpu"][1], grads["cpu, edges given"][1])
    assert_rel_close(grads["cpu"][0], grads["torch"][0], 1e-6, "loss")
    assert_rel_close(grads["cpu"][1], grads["torch"][1], 1e-5, "loss gradient")


def test_a_finished_build_is_imported_directly(extension, monkeypatch, tmp_path):
    """A later process imports the build named by its directory without torch's loader (which
    imports setuptools and runs ninja). Only a build marked finished is taken: a link killed
    midway leaves a truncated file, and loading one kills the process (SIGBUS)."""
    so = Path(extension.__file__)
    name = so.stem.split(".")[0]
    assert (so.parent / cpu_build._BUILT).exists()  # marked by the build this run loaded
    monkeypatch.setattr("torch.utils.cpp_extension.load", _no_torch_loader)
    cpu_backend.load_extension.cache_clear()
    try:
        again = cpu_backend.load_extension()
        assert again is not None and Path(again.__file__) == so
    finally:
        cpu_backend.load_extension.cache_clear()
    shutil.copy(so, tmp_path / so.name)
    assert cpu_build._load_built(tmp_path, name) is None  # not marked finished
    (tmp_path / cpu_build._BUILT).write_text("")
    os.utime(tmp_path / cpu_build._BUILT, (0, 0))
    assert cpu_build._load_built(tmp_path, name) is not None
    assert (tmp_path / cpu_build._BUILT).stat().st_mtime > 0  # its last use, for pruning


def _no_torch_loader(**_: object) -> None:
    raise AssertionError("torch's extension loader was used")


def test_builds_unused_for_30_days_are_removed(tmp_path):
    old_day = time.time() - 31 * 86400

    def build(name: str, mtime: float, marked: bool = True) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        files = [folder / "x.so", *([folder / cpu_build._BUILT] if marked else [])]
        for f in files:
            f.write_text("")
            os.utime(f, (mtime, mtime))
        return folder

    stale = build("ext-00000000000000aa", old_day)
    stale_unmarked = build("ext-00000000000000bb", old_day, marked=False)
    recent = build("ext-00000000000000cc", time.time() - 2 * 86400)
    used = build("ext-00000000000000dd", old_day)
    os.utime(used / cpu_build._BUILT)  # loaded today
    current = build("ext-00000000000000ee", old_day)
    other = build("ext-not-a-build", old_day)
    cpu_build._prune_cache(tmp_path, keep=current)
    assert not stale.exists() and not stale_unmarked.exists()
    assert recent.exists() and used.exists() and current.exists() and other.exists()
