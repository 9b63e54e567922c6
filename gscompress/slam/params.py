"""The map as trainable tensors: activation to render inputs, and Adam bookkeeping on resize.

`activate` is the one place where raw parameters (log scales, opacity logits, SH DC colour,
unnormalised quaternions) become the renderer's inputs; `gscompress.ops.score` uses it too.

`GaussianParams` holds the SLAM map as leaf tensors plus ids and PWAS sums. Adding Gaussians
(densification, a received share) and removing them (pruning) replace the leaf
tensors; `resize_adam_rows` moves the optimizer's per-Gaussian state along, so that the Adam
moments of every surviving Gaussian stay attached to it and new Gaussians start from zero.

`Adam` is the map's optimizer: torch's Adam update without torch.optim, whose first use imports
torch._dynamo (as long as importing torch itself, paid by every `gsc slam` and `gsc merge`;
measured in docs/design-experiments.md, "Start-up").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

from gscompress.gaussians import SH_C0, GaussianMap
from gscompress.importance import ImportanceSums

TRAINABLE = ("means", "log_scales", "quats", "opacity_logits", "sh_dc")
"""Names of the optimised per-Gaussian tensors, as in `GaussianMap`."""


class RenderInputs(NamedTuple):
    """Activated parameters in the order `gscompress.render.render` takes them."""

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4]
    scales: torch.Tensor  # [N, 3]
    opacities: torch.Tensor  # [N]
    colors: torch.Tensor  # [N, 3]


def activate(
    means: torch.Tensor,
    log_scales: torch.Tensor,
    quats: torch.Tensor,
    opacity_logits: torch.Tensor,
    sh_dc: torch.Tensor,
) -> RenderInputs:
    """Raw parameters -> render inputs (differentiable).

    Args:
        means: [N, 3] centres.
        log_scales: [N, 1] (isotropic) or [N, 3] log standard deviations.
        quats: [N, 4] unnormalised (w, x, y, z).
        opacity_logits: [N] opacity before the sigmoid.
        sh_dc: [N, 3] zeroth-order SH colour.

    Returns:
        means, quats, [N, 3] scales, [N] opacities and [N, 3] RGB (clamped at 0, as 3DGS does).
    """
    n = means.shape[0]
    return RenderInputs(
        means=means,
        quats=quats,
        scales=torch.exp(log_scales).expand(n, 3),
        opacities=torch.sigmoid(opacity_logits),
        colors=(0.5 + SH_C0 * sh_dc).clamp_min(0.0),
    )


def decay_per_step(final_fraction: float, iters: int) -> float:
    """The factor that takes a learning rate to `final_fraction` of itself at the last of
    `iters` steps when applied once after each step (the first step runs at the full rate, so a
    single step never decays)."""
    return final_fraction ** (1.0 / max(iters - 1, 1))


class Adam:
    """`torch.optim.Adam` (no weight decay, no amsgrad) on groups of tensors, without torch.optim.

    The same operations in the same order as torch's single-tensor CPU implementation, so the
    parameters come out bit for bit the same (tested). The attributes that
    `resize_adam_rows` works on are torch's: `param_groups` (dicts with "params" and "lr") and
    `state` (per parameter: "step", "exp_avg", "exp_avg_sq", created at its first step).

    Args:
        groups: dicts with "params" (a list of leaf tensors), "lr" and any other keys (kept).
        betas: decay rates of the first and second moments.
        eps: added to the second moment's root.
    """

    def __init__(
        self,
        groups: list[dict[str, Any]],
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        self.param_groups = [dict(group, params=list(group["params"])) for group in groups]
        self.betas = betas
        self.eps = eps
        self.row_rates: torch.Tensor | None = None
        """[N] factors on each row's step (None: 1 for every row); a refinement that keeps some
        Gaussians still (0) or slows them sets it. It must have one row per Gaussian while set
        (nothing added or removed meanwhile)."""
        self.state: dict[torch.Tensor, dict[str, Any]] = {}

    def zero_grad(self) -> None:
        """Drop every parameter's gradient (set it to None)."""
        for group in self.param_groups:
            for p in group["params"]:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        """One update of every parameter that has a gradient."""
        beta1, beta2 = self.betas
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state.get(p)
                if not state:
                    state = self.state[p] = {
                        "step": 0,
                        "exp_avg": torch.zeros_like(p),
                        "exp_avg_sq": torch.zeros_like(p),
                    }
                state["step"] += 1
                step = float(state["step"])
                exp_avg, exp_avg_sq = state["exp_avg"], state["exp_avg_sq"]
                exp_avg.lerp_(p.grad, 1 - beta1)
                exp_avg_sq.mul_(beta2).addcmul_(p.grad, p.grad, value=1 - beta2)
                step_size = group["lr"] / (1 - beta1**step)
                denom = (exp_avg_sq.sqrt() / (1 - beta2**step) ** 0.5).add_(self.eps)
                rates = self.row_rates
                if rates is None:
                    p.addcdiv_(exp_avg, denom, value=-step_size)
                else:
                    rows = rates.reshape(-1, *([1] * (p.dim() - 1)))
                    p.sub_(exp_avg / denom * rows * step_size)


def resize_adam_rows(
    optimizer: Adam,
    old: torch.Tensor,
    new: torch.Tensor,
    rows: Callable[[torch.Tensor], torch.Tensor],
) -> bool:
    """Replace parameter `old` by `new` in `optimizer`, mapping its per-row state with `rows`.

    Every state tensor whose first dimension is the old row count (Adam's exp_avg and
    exp_avg_sq) becomes `rows(state)`; scalars such as `step` are kept.

    Returns:
        False when `old` is not one of the optimizer's parameters (nothing changed).
    """
    for group in optimizer.param_groups:
        params = group["params"]
        for i, p in enumerate(params):
            if p is not old:
                continue
            params[i] = new
            state = optimizer.state.pop(old, None)
            if state:
                optimizer.state[new] = {
                    key: rows(value)
                    if isinstance(value, torch.Tensor)
                    and value.dim() > 0
                    and value.shape[0] == old.shape[0]
                    else value
                    for key, value in state.items()
                }
            return True
    return False


@dataclass
class GaussianParams:
    """The SLAM map as leaf tensors (on one device), with ids and PWAS running sums.

    Attributes:
        means: [N, 3]; log_scales: [N, 1|3]; quats: [N, 4]; opacity_logits: [N];
        sh_dc: [N, 3] — float32 leaves that require grad.
        ids: [N] int64 stable ids.
        sums: the PWAS sums of the same N Gaussians.
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor
    ids: torch.Tensor
    sums: ImportanceSums

    @classmethod
    def from_map(cls, gaussians: GaussianMap, device: str | torch.device = "cpu") -> GaussianParams:
        """Leaf tensors for a map (SH degree 0 is used; higher SH bands are dropped)."""
        t = gaussians.to_tensors(device)
        sums = ImportanceSums(
            t["importance_sum"].double(), t["importance_weight"].double(), t["alpha_t_sum"].double()
        )
        leaves = {name: t[name].detach().clone().requires_grad_(True) for name in TRAINABLE}
        return cls(ids=t["ids"], sums=sums, **leaves)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def isotropic(self) -> bool:
        """One scale per Gaussian."""
        return self.log_scales.shape[1] == 1

    def non_finite(self) -> list[str]:
        """The names of the trainable tensors holding a NaN or an infinity."""
        with torch.no_grad():
            return [name for name in TRAINABLE if not bool(getattr(self, name).isfinite().all())]

    def render_inputs(self) -> RenderInputs:
        """The activated parameters (differentiable w.r.t. the leaves)."""
        return activate(self.means, self.log_scales, self.quats, self.opacity_logits, self.sh_dc)

    def to_map(self) -> GaussianMap:
        """A numpy `GaussianMap` of the current state, importance sums included: a copy, which
        later steps of the parameters leave as it is."""

        def copy(x: torch.Tensor) -> np.ndarray:
            return np.array(x.detach().cpu().numpy())

        n = len(self)
        return GaussianMap.new(
            **{name: copy(getattr(self, name)) for name in TRAINABLE},
            sh_rest=np.zeros((n, 0, 3), np.float32),
            ids=self.ids.cpu().numpy().astype(np.uint32),
            importance_sum=copy(self.sums.importance_sum),
            importance_weight=copy(self.sums.importance_weight),
            alpha_t_sum=copy(self.sums.alpha_t_sum),
        )

    def append(self, gaussians: GaussianMap, optimizer: Adam | None) -> None:
        """Add Gaussians at the end (their Adam state starts at zero, sums as given)."""
        if self.isotropic and not gaussians.isotropic:
            self.widen(optimizer)
        elif gaussians.isotropic and not self.isotropic:
            gaussians = gaussians.as_anisotropic()
        extra = GaussianParams.from_map(gaussians, self.means.device)
        m = len(extra)

        def zeros_after(x: torch.Tensor) -> torch.Tensor:
            return torch.cat([x, x.new_zeros((m, *x.shape[1:]))])

        for name in TRAINABLE:
            tail: torch.Tensor = getattr(extra, name).detach()

            def values(x: torch.Tensor, tail: torch.Tensor = tail) -> torch.Tensor:
                return torch.cat([x, tail])

            self._replace(optimizer, (name,), values, zeros_after)
        self.ids = torch.cat([self.ids, extra.ids])
        self.sums = self.sums.extend(extra.sums)

    def widen(self, optimizer: Adam | None) -> None:
        """Give every Gaussian of an isotropic map three scales, each its one scale (the render
        is unchanged), with its Adam state alike (nothing to do on an anisotropic map)."""
        if not self.isotropic:
            return

        def columns(x: torch.Tensor) -> torch.Tensor:
            return x.expand(-1, 3).contiguous()

        self._replace(optimizer, ("log_scales",), columns, columns)

    def keep(self, index: torch.Tensor, optimizer: Adam | None) -> None:
        """Keep only the Gaussians at `index` (bool mask [N] or indices), with their state."""

        def rows(x: torch.Tensor) -> torch.Tensor:
            return x[index]

        self._replace(optimizer, TRAINABLE, rows, rows)
        self.ids = self.ids[index]
        self.sums = self.sums.select(index)

    def _replace(
        self,
        optimizer: Adam | None,
        names: tuple[str, ...],
        values: Callable[[torch.Tensor], torch.Tensor],
        state_rows: Callable[[torch.Tensor], torch.Tensor],
    ) -> None:
        """New leaves `values(old)` for `names`; their optimizer state maps by `state_rows`."""
        for name in names:
            old = getattr(self, name)
            new = values(old.detach()).detach().requires_grad_(True)
            if optimizer is not None:
                resize_adam_rows(optimizer, old, new, state_rows)
            setattr(self, name, new)
