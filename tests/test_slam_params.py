"""SLAM parameters: shared activation, and Adam state that follows its Gaussians."""

import numpy as np
import pytest
import torch

from gscompress.gaussians import random_map
from gscompress.ops.score import activated_tensors
from gscompress.slam.params import Adam, GaussianParams, activate, resize_adam_rows


def test_activation_matches_the_map_and_score():
    g = random_map(50, seed=3, isotropic=False)
    t = g.to_tensors()
    inputs = activate(t["means"], t["log_scales"], t["quats"], t["opacity_logits"], t["sh_dc"])
    np.testing.assert_allclose(inputs.scales.numpy(), g.scales(), rtol=1e-6)
    np.testing.assert_allclose(inputs.opacities.numpy(), g.opacities(), rtol=1e-6)
    np.testing.assert_allclose(inputs.colors.numpy(), np.maximum(g.colors(), 0), atol=1e-6)
    for name, value in activated_tensors(g).items():
        torch.testing.assert_close(value, getattr(inputs, name))


def groups(params, lrs=(1e-2, 1e-2, 1e-2, 1e-2)):
    """One optimizer group per trained tensor of an isotropic map, as the mapper makes them."""
    names = ("means", "sh_dc", "opacity_logits", "log_scales")
    return [{"params": [getattr(params, n)], "lr": lr} for n, lr in zip(names, lrs, strict=True)]


def step_with_row_gradients(params, optimizer):
    """One Adam step where each Gaussian's gradient is its id (so state rows are traceable)."""
    optimizer.zero_grad()
    ids = params.ids.double()
    loss = sum(
        (getattr(params, name) * ids.view(-1, *[1] * (getattr(params, name).dim() - 1))).sum()
        for name in ("means", "sh_dc", "opacity_logits", "log_scales")
    )
    loss.backward()
    optimizer.step()


def test_adam_rows_follow_their_gaussians_through_remove_and_add():
    params = GaussianParams.from_map(random_map(40, seed=0))
    opt = Adam(groups(params))
    for _ in range(3):
        step_with_row_gradients(params, opt)
    before = {
        int(i): opt.state[params.means]["exp_avg"][k].clone() for k, i in enumerate(params.ids)
    }
    old_means = params.means.detach().clone()
    keep = torch.arange(40) % 3 != 0
    params.keep(keep, opt)
    assert len(params) == int(keep.sum())
    np.testing.assert_array_equal(params.means.detach().numpy(), old_means[keep].numpy())
    extra = random_map(7, seed=9)
    params.append(extra, opt)
    assert len(params) == int(keep.sum()) + 7
    state = opt.state[params.means]
    for k, i in enumerate(params.ids.tolist()[:-7]):
        torch.testing.assert_close(state["exp_avg"][k], before[i])
    assert float(state["exp_avg"][-7:].abs().max()) == 0.0
    assert float(state["exp_avg_sq"][-7:].abs().max()) == 0.0
    np.testing.assert_array_equal(params.means[-7:].detach().numpy(), extra.means)
    # the optimizer holds the new leaves and keeps working
    assert opt.param_groups[0]["params"][0] is params.means
    step_with_row_gradients(params, opt)
    assert opt.state[params.means]["exp_avg"].shape == (len(params), 3)
    # sums and ids followed too
    assert params.sums.importance_sum.shape == (len(params),)
    m = params.to_map()
    np.testing.assert_array_equal(m.ids[-7:], extra.ids)
    np.testing.assert_allclose(m.importance_sum[-7:], extra.importance_sum, rtol=1e-6)


def test_resize_ignores_foreign_tensors_and_promotes_isotropic():
    params = GaussianParams.from_map(random_map(5, seed=1))
    opt = Adam([{"params": [params.log_scales], "lr": 1e-2}])
    assert not resize_adam_rows(opt, torch.zeros(5), torch.zeros(5), lambda x: x)
    params.log_scales.sum().backward()
    opt.step()
    params.append(random_map(2, seed=2, isotropic=False), opt)
    assert params.log_scales.shape == (7, 3)
    assert opt.state[params.log_scales]["exp_avg"].shape == (7, 3)


def test_adam_equals_torch_adam_bit_for_bit_through_remove_and_add():
    """The map's Adam follows torch.optim.Adam exactly (same operations, same order), with
    per-group learning rates, gradients that change every step, a parameter left without a
    gradient, and Gaussians removed and added between steps."""
    runs = []
    for make in (lambda g: torch.optim.Adam(g, eps=1e-15), lambda g: Adam(g, eps=1e-15)):
        params = GaussianParams.from_map(random_map(60, seed=4))
        opt = make(groups(params, (1e-3, 2e-2, 5e-2, 1e-3)))
        weights = torch.Generator().manual_seed(0)
        for step in range(12):
            if step == 4:
                params.keep(torch.arange(len(params)) % 4 != 1, opt)
            if step == 8:
                params.append(random_map(9, seed=5), opt)
            opt.zero_grad()
            names = ("means", "sh_dc", "log_scales") + (("opacity_logits",) if step % 3 else ())
            loss = 0.0
            for name in names:
                x = getattr(params, name)
                w = torch.randn(x.shape, generator=weights, dtype=x.dtype)
                loss = loss + (w * x + x * x * x.abs()).sum()
            loss.backward()
            opt.step()
        runs.append(params)
    for name in ("means", "sh_dc", "opacity_logits", "log_scales"):
        assert torch.equal(getattr(runs[0], name), getattr(runs[1], name)), name


@pytest.mark.parametrize("isotropic", [True, False])
def test_to_map_round_trip(isotropic):
    g = random_map(30, seed=5, isotropic=isotropic)
    assert GaussianParams.from_map(g).to_map().equals(g)


def test_a_map_taken_from_the_params_is_a_copy_that_later_steps_leave_alone():
    params = GaussianParams.from_map(random_map(20, seed=5))
    optimizer = Adam(groups(params))
    before = params.to_map()
    means = before.means.copy()
    step_with_row_gradients(params, optimizer)
    assert not np.array_equal(params.means.detach().numpy(), means)  # (the step moved them)
    np.testing.assert_array_equal(before.means, means)
