"""The C++ compositing kernels against the pure-torch oracle: values, gradients, contribution."""

from __future__ import annotations

import warnings

import pytest
import torch
from test_render import (
    ARGS,
    _pose_function,
    assert_rel_close,
    loss_weights,
    make_scene,
    outputs_loss,
    run,
)

from gscompress.render import cpu as cpu_backend
from gscompress.render import resolve_backend

INPUTS = (*ARGS, "T_cam_world")
TOL = {torch.float64: 1e-10, torch.float32: 1e-5}


@pytest.fixture(scope="module", autouse=True)
def extension():
    """Build (or load) the extension once for this module; skip without a compiler."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ext = cpu_backend.load_extension()
    if ext is None:
        pytest.skip("the C++ render kernels could not be built (no compiler?)")
    return ext


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
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one, g_one = _render_and_grads(scene, "cpu", want_contribution=True)
        torch.set_num_threads(2)
        two, g_two = _render_and_grads(scene, "cpu", want_contribution=True)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one.color, two.color)
    assert torch.equal(one.contribution, two.contribution)
    for key in ("opacities", "colors"):  # direct kernel outputs, before any torch reduction
        assert torch.equal(g_one[key], g_two[key]), key


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
    with cpu_backend._build_lock(tmp_path):
        assert not stale.exists()
        # another process cannot enter while this one builds
        probe = (
            "import fcntl, sys; f = open(sys.argv[1], 'w')\n"
            "try: fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)\n"
            "except BlockingIOError: sys.exit(3)"
        )
        held = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "gsc.lock")])
        assert held.returncode == 3
