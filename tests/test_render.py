"""The pure-torch rasterizer against an independent dense implementation, gradients, edge cases.

`dense_render` below is written from the spec in `gscompress.render` without tiles: every
Gaussian against every pixel, one Gaussian at a time in depth order. Other render test modules
import `make_scene` and `dense_render` from here.
"""

from __future__ import annotations

import importlib.machinery
import sys
import types

import pytest
import torch

from gscompress.camera import Intrinsics
from gscompress.errors import InputError, MissingDependencyError
from gscompress.render import RenderOutput, render, resolve_backend, resolve_device
from gscompress.render.projection import bin_tiles, project_gaussians

INTR = Intrinsics(fx=28.0, fy=27.0, cx=15.5, cy=11.5, width=32, height=24)
ARGS = ("means", "quats", "scales", "opacities", "colors")


def pose(rx: float, ry: float, rz: float, tx: float, ty: float, tz: float, dtype) -> torch.Tensor:
    """A 4x4 rigid transform from an axis-angle rotation and a translation."""
    twist = torch.zeros(4, 4, dtype=torch.float64)
    twist[0, 1], twist[0, 2], twist[1, 2] = -rz, ry, -rx
    twist[1, 0], twist[2, 0], twist[2, 1] = rz, -ry, rx
    T = torch.linalg.matrix_exp(twist)
    T[:3, 3] = torch.tensor([tx, ty, tz], dtype=torch.float64)
    return T.to(dtype)


def make_scene(
    n: int = 300, seed: int = 0, dtype=torch.float64, scale: float = 1.0
) -> dict[str, torch.Tensor]:
    """Random Gaussians in front of (mostly) and around the camera of `INTR`, with a pose."""
    g = torch.Generator().manual_seed(seed)

    def u(*shape, lo=0.0, hi=1.0):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)

    z = u(n, lo=-0.3, hi=4.0)  # some behind the camera, some in front of near
    xy = u(n, 2, lo=-0.9, hi=0.9) * z.abs()[:, None].clamp(min=0.5)
    cam_points = torch.cat([xy, z[:, None]], dim=1)
    T_cam_world = pose(0.05, -0.1, 0.03, 0.1, -0.05, 0.2, torch.float64)
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    means = (cam_points - t) @ R  # world = R^T (cam - t)
    opacities = u(n, lo=0.05, hi=0.999)
    opacities[: n // 10] = 0.999  # saturate the 0.99 clamp on some
    scene = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "scales": u(n, 3, lo=0.02, hi=0.25) * scale,
        "opacities": opacities,
        "colors": u(n, 3),
        "T_cam_world": T_cam_world,
    }
    return {k: v.to(dtype) for k, v in scene.items()}


def run(scene, backend="torch", **kw) -> RenderOutput:
    return render(*(scene[k] for k in ARGS), INTR, scene["T_cam_world"], backend=backend, **kw)


def dense_render(scene, intr=INTR, near=0.01, background=None):
    """Independent all-Gaussians x all-pixels renderer; returns (dict of images, contribution)."""
    means, quats, scales = scene["means"], scene["quats"], scene["scales"]
    opac, colors, T = scene["opacities"], scene["colors"], scene["T_cam_world"]
    W, H = intr.width, intr.height
    p = means @ T[:3, :3].T + T[:3, 3]
    z = p[:, 2]
    front = z >= near
    zs = torch.where(front, z, torch.ones_like(z))
    q = quats / quats.norm(dim=1, keepdim=True)
    w, v = q[:, 0], q[:, 1:]
    eye = torch.eye(3, dtype=means.dtype)
    cross = torch.zeros(len(q), 3, 3, dtype=means.dtype)
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    cross = cross - cross.transpose(1, 2)
    # Rodrigues form of a unit quaternion's rotation.
    Rg = (
        (w * w - (v * v).sum(1))[:, None, None] * eye
        + 2 * v[:, :, None] * v[:, None, :]
        + 2 * w[:, None, None] * cross
    )
    cov = Rg @ torch.diag_embed(scales**2) @ Rg.transpose(1, 2)
    cov_c = T[:3, :3] @ cov @ T[:3, :3].T
    # border: the outer pixel edges at -0.5 and W - 0.5 (pixel centres at 0 .. W - 1)
    limx = ((intr.cx + 0.5 + 0.15 * W) / intr.fx, (W - 0.5 - intr.cx + 0.15 * W) / intr.fx)
    limy = ((intr.cy + 0.5 + 0.15 * H) / intr.fy, (H - 0.5 - intr.cy + 0.15 * H) / intr.fy)
    xc = zs * torch.clamp(p[:, 0] / zs, -limx[0], limx[1])
    yc = zs * torch.clamp(p[:, 1] / zs, -limy[0], limy[1])
    J = torch.zeros(len(q), 2, 3, dtype=means.dtype)
    J[:, 0, 0], J[:, 0, 2] = intr.fx / zs, -intr.fx * xc / zs**2
    J[:, 1, 1], J[:, 1, 2] = intr.fy / zs, -intr.fy * yc / zs**2
    cov2 = J @ cov_c @ J.transpose(1, 2) + 0.3 * torch.eye(2, dtype=means.dtype)
    cov2 = 0.5 * (cov2 + cov2.transpose(1, 2))
    conic = torch.linalg.inv(cov2)
    mu = torch.stack([intr.fx * p[:, 0] / zs + intr.cx, intr.fy * p[:, 1] / zs + intr.cy], 1)
    radius = torch.ceil(3 * torch.sqrt(torch.linalg.eigvalsh(cov2.detach())[:, 1]))

    jj, ii = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    px, py = ii.reshape(-1).to(means.dtype), jj.reshape(-1).to(means.dtype)  # [P]
    tile_u0, tile_v0 = (ii.reshape(-1) // 16) * 16, (jj.reshape(-1) // 16) * 16  # [P]
    P = H * W
    T_pix = torch.ones(P, dtype=means.dtype)
    acc = torch.zeros(P, 4, dtype=means.dtype)
    done = torch.zeros(P, dtype=torch.bool)
    contrib = torch.zeros(len(q), dtype=means.dtype)
    for i in torch.argsort(z.detach(), stable=True).tolist():
        if not front[i]:
            continue
        um, vm, r = mu[i, 0].detach(), mu[i, 1].detach(), radius[i]
        # The pixel's tile intersects [u - r, u + r] x [v - r, v + r] (in pixel centres).
        covered_u = (tile_u0 <= um + r) & (tile_u0 + 15 >= um - r)
        covered = covered_u & (tile_v0 <= vm + r) & (tile_v0 + 15 >= vm - r)
        dx, dy = px - mu[i, 0], py - mu[i, 1]
        a, b, c = conic[i, 0, 0], conic[i, 0, 1], conic[i, 1, 1]
        alpha = torch.clamp(
            opac[i] * torch.exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy), max=0.99
        )
        use = covered & ~done & (alpha >= 1 / 255)
        stop = use & (T_pix * (1 - alpha) < 1e-4)
        done = done | stop
        alpha = torch.where(use & ~stop, alpha, torch.zeros_like(alpha))
        weight = alpha * T_pix
        acc = acc + weight[:, None] * torch.cat([colors[i], z[i : i + 1]])
        contrib[i] = weight.detach().sum()
        T_pix = T_pix * (1 - alpha)
    sil = (1 - T_pix).reshape(H, W)
    color = acc[:, :3].reshape(H, W, 3)
    if background is not None:
        color = color + T_pix.reshape(H, W, 1) * background
    depth = acc[:, 3].reshape(H, W)
    out = {
        "color": color,
        "depth": depth,
        "silhouette": sil,
        "depth_normalized": depth / sil.clamp(min=1e-10),
    }
    return out, contrib


def outputs_loss(out, weights) -> torch.Tensor:
    """A scalar mixing every differentiable output (RenderOutput or dict) with fixed weights."""
    images = out if isinstance(out, dict) else {k: getattr(out, k) for k in weights}
    return sum((images[k] * w).sum() for k, w in weights.items())


def loss_weights(dtype=torch.float64, seed=1):
    g = torch.Generator().manual_seed(seed)
    H, W = INTR.height, INTR.width
    return {
        "color": torch.rand(H, W, 3, generator=g, dtype=torch.float64).to(dtype),
        "depth": torch.rand(H, W, generator=g, dtype=torch.float64).to(dtype),
        "silhouette": torch.rand(H, W, generator=g, dtype=torch.float64).to(dtype),
        "depth_normalized": torch.rand(H, W, generator=g, dtype=torch.float64).to(dtype),
    }


def assert_rel_close(actual, expected, tol, what=""):
    scale = max(expected.abs().max().item(), 1e-12)
    err = (actual - expected).abs().max().item()
    assert err <= tol * scale, f"{what}: max abs error {err:.3e} vs scale {scale:.3e}"


# --- projection -------------------------------------------------------------------------------


def test_projection_culls_behind_near_and_offscreen():
    scene = make_scene(400, seed=3)
    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["T_cam_world"], INTR, 0.01
    )
    z = proj.depths
    assert (proj.radii[z < 0.01] == 0).all()
    assert (proj.radii > 0).sum() > 100
    vis = proj.radii > 0
    u, v, r = proj.means2d[vis, 0], proj.means2d[vis, 1], proj.radii[vis]
    # Every kept footprint reaches a tile: 2 x 2 tiles of 16 px cover pixel centres 0..31.
    assert ((u + r >= 0) & (u - r <= 31) & (v + r >= 0) & (v - r <= 31)).all()
    assert (~vis & (z >= 0.01)).sum() > 10  # in front of the camera but off-screen


def test_tile_lists_are_depth_sorted_and_cover_footprints():
    scene = make_scene(300, seed=4)
    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["T_cam_world"], INTR, 0.01
    )
    bins = bin_tiles(proj, INTR.width, INTR.height)
    assert bins.offsets[-1] == len(bins.ids) > 0
    for t in range(bins.tiles_x * bins.tiles_y):
        ids = bins.ids[bins.offsets[t] : bins.offsets[t + 1]]
        assert (proj.depths[ids].diff() >= 0).all()
        tx, ty = t % bins.tiles_x, t // bins.tiles_x
        u, v, r = proj.means2d[ids, 0], proj.means2d[ids, 1], proj.radii[ids]
        assert ((u + r >= 16 * tx) & (u - r <= 16 * tx + 15)).all()
        assert ((v + r >= 16 * ty) & (v - r <= 16 * ty + 15)).all()


# --- values and gradients against the dense renderer ------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_torch_backend_equals_dense(seed):
    scene = make_scene(300, seed=seed)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = run(scene, want_contribution=True, background=bg)
    ref, contrib = dense_render(scene, background=bg)
    assert out.backend == "torch"
    for key, expected in ref.items():
        assert_rel_close(getattr(out, key), expected, 1e-12, key)
    assert_rel_close(out.contribution, contrib, 1e-12, "contribution")
    assert out.silhouette.max() > 0.99  # deep enough to reach the stopping rule


def test_contribution_is_explicit_sum_of_alpha_T():
    scene = make_scene(200, seed=5)
    out = run(scene, want_contribution=True)
    _, contrib = dense_render(scene)
    assert (contrib[~out.visible] == 0).all()
    assert contrib.sum() > 1.0
    assert_rel_close(out.contribution, contrib, 1e-12, "contribution")
    # The sum over Gaussians of alpha*T is the summed silhouette.
    assert torch.isclose(out.contribution.sum(), out.silhouette.sum(), rtol=1e-12)


def test_torch_backend_gradients_equal_dense():
    scene = make_scene(150, seed=6)
    for v in scene.values():
        v.requires_grad_(True)
    weights = loss_weights()
    inputs = [scene[k] for k in (*ARGS, "T_cam_world")]
    grads = torch.autograd.grad(outputs_loss(run(scene), weights), inputs)
    ref = torch.autograd.grad(outputs_loss(dense_render(scene)[0], weights), inputs)
    for name, got, expected in zip((*ARGS, "T_cam_world"), grads, ref, strict=True):
        assert expected.abs().max() > 0, name
        assert_rel_close(got, expected, 1e-10, name)


def _pose_function(scene, backend):
    weights = loss_weights()
    T0 = scene["T_cam_world"].detach()

    def f(xi):
        twist = torch.zeros(4, 4, dtype=torch.float64)
        twist[0, 1], twist[0, 2], twist[1, 2] = -xi[2], xi[1], -xi[0]
        twist[1, 0], twist[2, 0], twist[2, 1] = xi[2], -xi[1], xi[0]
        twist[:3, 3] = xi[3:]
        T = torch.linalg.matrix_exp(twist) @ T0
        out = render(*(scene[k] for k in ARGS), INTR, T, backend=backend)
        return torch.stack([(getattr(out, k) * w).sum() for k, w in weights.items()])

    return f


def test_gradcheck_camera_pose_torch():
    scene = {k: v.detach() for k, v in make_scene(40, seed=7).items()}
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(_pose_function(scene, "torch"), (xi,), eps=1e-6, atol=1e-6)


def test_gradcheck_means_and_scales_torch():
    scene = {k: v.detach() for k, v in make_scene(12, seed=8, scale=2.0).items()}
    weights = loss_weights()

    def f(means, scales, quats):
        out = render(
            means,
            quats,
            scales,
            scene["opacities"],
            scene["colors"],
            INTR,
            scene["T_cam_world"],
            backend="torch",
        )
        return torch.stack([(getattr(out, k) * w).sum() for k, w in weights.items()])

    args = tuple(scene[k].clone().requires_grad_(True) for k in ("means", "scales", "quats"))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6)


# --- the compositing rules, checked by hand ---------------------------------------------------


def stacked_scene(dtype, opacity=0.95, count=6):
    """`count` small Gaussians exactly on pixel (10, 5), one behind the other."""
    z = torch.arange(1, count + 1, dtype=torch.float64)
    u, v = (10 - INTR.cx) / INTR.fx, (5 - INTR.cy) / INTR.fy
    scene = {
        "means": torch.stack([u * z, v * z, z], dim=1),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(count, 1).double(),
        "scales": torch.full((count, 3), 1e-3, dtype=torch.float64) * z[:, None],
        "opacities": torch.full((count,), opacity, dtype=torch.float64),
        "colors": torch.rand(count, 3, generator=torch.Generator().manual_seed(0)).double(),
        "T_cam_world": torch.eye(4, dtype=torch.float64),
    }
    return {k: t.to(dtype) for k, t in scene.items()}


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_stopping_gaussian_is_left_out(backend):
    scene = stacked_scene(torch.float64)
    out = run(scene, backend=backend, want_contribution=True)
    # T: 1 -> 0.05 -> 0.0025 -> 1.25e-4; the 4th would give 6.25e-6 < 1e-4: stop, left out.
    w = torch.tensor([0.95, 0.95 * 0.05, 0.95 * 0.0025], dtype=torch.float64)
    expected = (w[:, None] * scene["colors"][:3]).sum(0)
    torch.testing.assert_close(out.color[5, 10], expected, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(out.silhouette[5, 10], torch.tensor(1 - 1.25e-4).double())
    torch.testing.assert_close(out.depth[5, 10], (w * torch.arange(1.0, 4.0).double()).sum())
    assert out.silhouette.min() >= 0 and (1 - out.silhouette).min() >= 1e-4


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_alpha_clamp_and_skip_threshold(backend):
    scene = stacked_scene(torch.float64, opacity=0.999, count=1)
    out = run(scene, backend=backend)
    assert out.silhouette[5, 10].item() == pytest.approx(0.99, abs=1e-12)
    faint = stacked_scene(torch.float64, opacity=0.5 / 255, count=3)
    assert run(faint, backend=backend).silhouette.abs().max() == 0


# --- edge cases -------------------------------------------------------------------------------


def _empty(dtype):
    return {
        "means": torch.zeros(0, 3, dtype=dtype),
        "quats": torch.zeros(0, 4, dtype=dtype),
        "scales": torch.zeros(0, 3, dtype=dtype),
        "opacities": torch.zeros(0, dtype=dtype),
        "colors": torch.zeros(0, 3, dtype=dtype),
        "T_cam_world": torch.eye(4, dtype=dtype),
    }


def _behind(dtype):
    scene = make_scene(50, seed=9, dtype=dtype)
    scene["T_cam_world"] = pose(0, 3.14159, 0, 0, 0, -2.0, dtype)  # looking away
    return scene


def _offscreen(dtype):
    scene = make_scene(50, seed=10, dtype=dtype)
    scene["means"] = scene["means"] + torch.tensor([40.0, 0, 0], dtype=dtype)
    return scene


def _single(dtype):
    scene = make_scene(1, seed=11, dtype=dtype)
    scene["means"] = torch.tensor([[0.1, -0.05, 2.0]], dtype=dtype)
    scene["T_cam_world"] = torch.eye(4, dtype=dtype)
    return scene


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["empty", "behind", "offscreen", "single"])
def test_edge_cases_are_well_defined(case, dtype, backend):
    scene = {"empty": _empty, "behind": _behind, "offscreen": _offscreen, "single": _single}[case](
        dtype
    )
    for v in scene.values():
        v.requires_grad_(True)
    bg = torch.tensor([0.3, 0.6, 0.1], dtype=dtype)
    out = run(scene, backend=backend, want_contribution=True, background=bg)
    n = len(scene["means"])
    assert out.color.shape == (24, 32, 3) and out.depth.shape == (24, 32)
    assert out.radii.shape == (n,) and out.contribution.shape == (n,)
    assert out.color.dtype == dtype
    inputs = [scene[k] for k in (*ARGS, "T_cam_world")]
    grads = torch.autograd.grad(outputs_loss(out, loss_weights(dtype)), inputs)
    assert all(torch.isfinite(g).all() for g in grads)
    if case == "single":
        assert out.visible.all() and 0.5 < out.silhouette.max() <= 0.99
        assert out.contribution[0] > 0 and grads[0].abs().sum() > 0
        return
    assert not out.visible.any()
    torch.testing.assert_close(out.color, bg.expand(24, 32, 3))
    for key in ("depth", "silhouette", "depth_normalized"):
        assert (getattr(out, key) == 0).all(), key
    assert all((g == 0).all() for g in grads)


def test_float32_matches_float64():
    scene = make_scene(300, seed=12)
    out64 = run(scene)
    out32 = run({k: v.float() for k, v in scene.items()})
    assert out32.color.dtype == torch.float32
    assert_rel_close(out32.color.double(), out64.color, 1e-3, "color")
    assert_rel_close(out32.depth.double(), out64.depth, 1e-3, "depth")


# --- the front door ---------------------------------------------------------------------------


def test_bad_inputs_raise_input_error():
    scene = make_scene(10)
    with pytest.raises(InputError, match="unknown render backend"):
        run(scene, backend="vulkan")
    bad = dict(scene, quats=scene["quats"][:, :3])
    with pytest.raises(InputError, match=r"quats must have shape \[N, 4\]"):
        run(bad)
    with pytest.raises(InputError, match="float32 or float64"):
        run(dict(scene, colors=scene["colors"].half()))
    with pytest.raises(InputError, match="but means is"):
        run(dict(scene, colors=scene["colors"].float()))
    with pytest.raises(InputError, match="near must be positive"):
        run(scene, near=0.0)


@pytest.fixture()
def gsplat_reloaded():
    """Forget the loaded-or-failed outcome of gsplat's kernels before and after the test."""
    from gscompress.render.gsplat_backend import gsplat_kernels

    gsplat_kernels.cache_clear()
    yield
    gsplat_kernels.cache_clear()


def test_gsplat_backend_without_gsplat_raises(monkeypatch, gsplat_reloaded):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # makes `import gsplat` fail
    with pytest.raises(MissingDependencyError, match=r"pip install gscompress\[gpu\]"):
        resolve_backend("gsplat", torch.device("cuda"))
    assert resolve_backend("auto", torch.device("cuda")) == "torch"
    with pytest.raises(InputError, match="needs CUDA tensors"):  # the device is checked first
        run(make_scene(10), backend="gsplat")


@pytest.mark.parametrize("failure", ["no CUDA toolkit", "build fails"])
def test_gsplat_without_its_cuda_kernels(monkeypatch, caplog, gsplat_reloaded, failure):
    for name in ("gsplat", "gsplat.cuda"):
        module = types.ModuleType(name)
        module.__spec__ = importlib.machinery.ModuleSpec(name, None)
        module.rasterization = None  # type: ignore[attr-defined]
        monkeypatch.setitem(sys.modules, name, module)
    backend = types.ModuleType("gsplat.cuda._backend")
    attempts: list[str] = []
    if failure == "no CUDA toolkit":  # gsplat then sets _C to None
        backend._C = None  # type: ignore[attr-defined]
        expected = "no CUDA toolkit"
    else:  # torch's extension build raises while gsplat.cuda._backend is imported

        def build(name: str) -> object:
            attempts.append(name)
            raise RuntimeError("Error building extension 'gsplat_cuda'")

        backend.__getattr__ = build  # type: ignore[attr-defined]
        expected = "RuntimeError: Error building extension"
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", backend)
    cuda = torch.device("cuda")
    for _ in range(2):
        with pytest.raises(
            MissingDependencyError, match=f"could not be loaded or built.*{expected}"
        ):
            resolve_backend("gsplat", cuda)  # as before a timed loop
        assert resolve_backend("auto", cuda) == "torch"  # as the cpu backend falls back
    # one attempt and one warning, not one per render
    assert len(attempts) == (failure == "build fails")
    assert sum("could not be loaded" in r.getMessage() for r in caplog.records) == 1


def test_auto_picks_a_cpu_backend_for_cpu_tensors():
    picked = resolve_backend("auto", torch.device("cpu"))
    assert picked in ("cpu", "torch")
    assert run(make_scene(10), backend="auto").backend == picked
    assert resolve_backend("torch", torch.device("meta")) == "torch"
    with pytest.raises(InputError, match="needs CPU tensors"):
        resolve_backend("cpu", torch.device("meta"))
    with pytest.raises(InputError, match="unknown render backend"):
        resolve_backend("vulkan", torch.device("cpu"))


def test_auto_device_follows_the_render_backend():
    cuda = torch.cuda.is_available()
    assert resolve_device("auto", "cpu") == torch.device("cpu")  # the C++ kernels need the CPU
    assert resolve_device("auto", "torch").type == ("cuda" if cuda else "cpu")
    assert resolve_device("cpu", "torch") == torch.device("cpu")
    if cuda:
        assert resolve_device("auto", "gsplat").type == "cuda"
    else:
        with pytest.raises(InputError, match="gsplat' renders on CUDA"):
            resolve_device("auto", "gsplat")
        with pytest.raises(InputError, match="torch sees no CUDA device"):
            resolve_device("cuda")


# --- gsplat (CUDA) ----------------------------------------------------------------------------


def _has_gsplat_cuda() -> bool:
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


gpu = pytest.mark.skipif(not _has_gsplat_cuda(), reason="needs CUDA and gsplat")


def faint(scene: dict[str, torch.Tensor], seed: int = 99) -> dict[str, torch.Tensor]:
    """The scene with opacities drawn in [0.05, 0.35]. Below 0.353 a Gaussian's alpha is under
    1/255 (skipped) beyond 3 sigma, so gsplat's opacity-sized tile footprints (up to 3.33 sigma)
    and the 3-sigma footprints of the other backends composite the same Gaussians everywhere."""
    g = torch.Generator().manual_seed(seed)
    o = 0.05 + 0.3 * torch.rand(scene["opacities"].shape, generator=g, dtype=torch.float64)
    return dict(scene, opacities=o.to(scene["opacities"].dtype))


def cuda_scene(scene: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.float().cuda().requires_grad_(True) for k, v in scene.items()}


@pytest.mark.gpu
@gpu
@pytest.mark.parametrize("seed", [13, 21])
def test_gsplat_equals_torch_backend_values_and_gradients(seed):
    scene = cuda_scene(faint(make_scene(300, seed=seed)))
    bg = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    ours = run(scene, backend="torch", want_contribution=True, background=bg)
    theirs = run(scene, backend="gsplat", want_contribution=True, background=bg)
    assert theirs.backend == "gsplat"
    # the same Gaussians count as visible (PWAS weights), those across the image edge included
    assert theirs.visible.sum() > 100 and not theirs.visible.all()
    assert torch.equal(theirs.radii, ours.radii)
    for key in ("color", "depth", "silhouette", "depth_normalized", "contribution"):
        assert_rel_close(getattr(theirs, key), getattr(ours, key), 1e-5, key)
    weights = {k: v.cuda() for k, v in loss_weights(torch.float32).items()}
    inputs = [scene[k] for k in (*ARGS, "T_cam_world")]
    grads = torch.autograd.grad(outputs_loss(theirs, weights), inputs)
    ref = torch.autograd.grad(outputs_loss(ours, weights), inputs)
    for name, got, expected in zip((*ARGS, "T_cam_world"), grads, ref, strict=True):
        assert expected.abs().max() > 0, name
        assert_rel_close(got, expected, 1e-4, name)


@pytest.mark.gpu
@gpu
def test_gsplat_on_cuda_renders_as_the_cpu_backend_on_the_cpu():
    # a map drawn on a GPU machine and on a CPU-only one: gsplat against the C++ kernels, each
    # on its own device, float32 on both
    scene = faint(make_scene(300, seed=7))
    ours = run({k: v.float() for k, v in scene.items()}, backend="cpu", want_contribution=True)
    theirs = run(cuda_scene(scene), backend="gsplat", want_contribution=True)
    assert (ours.backend, theirs.backend) == ("cpu", "gsplat")
    assert ours.contribution.sum() > 0
    for key in ("color", "depth", "silhouette", "depth_normalized", "contribution"):
        got = getattr(theirs, key).detach().cpu()
        assert_rel_close(got, getattr(ours, key), 1e-4, key)


@pytest.mark.gpu
@gpu
def test_gsplat_differs_only_where_opacity_exceeds_the_cap():
    # A tenth of this scene has opacity 0.999, capped at 0.99 before gsplat: there alpha is
    # 0.99 G instead of min(0.99, 0.999 G), slightly fainter edges; the rest agrees as above.
    scene = cuda_scene(make_scene(300, seed=13))
    ours = run(scene, backend="torch", want_contribution=True)
    theirs = run(scene, backend="gsplat", want_contribution=True)
    for key in ("color", "depth", "silhouette"):
        assert_rel_close(getattr(theirs, key), getattr(ours, key), 2e-2, key)
    rel = (ours.contribution - theirs.contribution).abs().sum() / ours.contribution.sum()
    assert rel < 2e-3
    # an opaque Gaussian lets 1% through on every backend (opacity capped at 0.99 for gsplat)
    solo = cuda_scene(stacked_scene(torch.float32, opacity=0.999, count=1))
    for out in (run(solo, backend="gsplat"), run(solo, backend="torch")):
        assert out.silhouette[5, 10].item() == pytest.approx(0.99, abs=1e-4)
