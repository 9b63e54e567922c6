"""Mapping: optimise the Gaussians over a window of views with fixed poses (paper Eq. 2-3).

The `Mapper` owns the map's leaf tensors and one Adam optimizer (`gscompress.slam.params.Adam`)
that lives for the whole run (one parameter group per tensor, with its own learning rate).
Gaussians are added by densification and removed by pruning between or during iterations; the
optimizer's moments follow their Gaussians (`gscompress.slam.params.resize_adam_rows`). Each
iteration renders one view: the current frame, or with probability 1 - `current_frame_share` a
keyframe of the window. Every `opacity_every` mapping iterations (counted over the run)
Gaussians with opacity below `alpha_min` and huge ones are removed (paper Eq. 9, SplaTAM's
cleanup). With `PoseConfig` on, an iteration on a view whose pose is open (`View.pose`) also
steps that pose along the same loss (`PoseConfig.window` in mapping, never the frame being
mapped; `PoseConfig.final` in the final refinement).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from gscompress.camera import Intrinsics
from gscompress.errors import DivergenceError
from gscompress.gaussians import SH_C0, GaussianMap
from gscompress.render import render
from gscompress.slam.config import SlamConfig
from gscompress.slam.keyframes import View
from gscompress.slam.losses import LossTerms, mapping_loss
from gscompress.slam.params import Adam, GaussianParams, decay_per_step

TOO_HIGH = "lower its learning rates, mapping.lr_* (or check the loss weights and intrinsics)"


@dataclass
class MappingStats:
    """What one mapping call did (losses averaged over its iterations).

    Attributes:
        iters: iterations run.
        loss, color, depth, illum, w_illum: mean total loss, its terms and the illum weight.
        first_loss, last_loss: total loss of the first and the last iteration.
        removed: Gaussians removed by the cyclic cleanup during these iterations.
        added: Gaussians added before these iterations (refill after a pruning stage).
    """

    iters: int = 0
    loss: float = 0.0
    color: float = 0.0
    depth: float = 0.0
    illum: float = 0.0
    w_illum: float = 0.0
    first_loss: float = 0.0
    last_loss: float = 0.0
    removed: int = 0
    added: int = 0

    def averaged(self) -> MappingStats:
        """These stats with the summed losses divided by the iterations (in place)."""
        if self.iters:
            for name in ("loss", "color", "depth", "illum", "w_illum"):
                setattr(self, name, getattr(self, name) / self.iters)
        return self


class Mapper:
    """The map's parameters, their optimizer and the mapping iterations.

    Args:
        config: the SLAM configuration (mapping learning rates and loss, cleanup settings).
        intrinsics: camera intrinsics at the working size.
        device: torch device of the map.
    """

    def __init__(self, config: SlamConfig, intrinsics: Intrinsics, device: torch.device) -> None:
        self.config = config
        self.intrinsics = intrinsics
        self.device = device
        self.params = GaussianParams.from_map(GaussianMap.empty(config.isotropic), device)
        m = config.mapping
        p = self.params
        groups = [
            {"params": [p.means], "lr": m.lr_means, "name": "means"},
            {"params": [p.sh_dc], "lr": m.lr_colors / SH_C0, "name": "sh_dc"},
            {"params": [p.opacity_logits], "lr": m.lr_opacity_logits, "name": "opacity_logits"},
            {"params": [p.log_scales], "lr": m.lr_log_scales, "name": "log_scales"},
        ]
        self.optimizer = Adam(groups, eps=1e-15)
        if not config.isotropic:
            self._open_rotations()
        self.iterations = 0
        self.scene_radius: float | None = None

    def __len__(self) -> int:
        return len(self.params)

    def add(self, gaussians: GaussianMap) -> int:
        """Append Gaussians (fresh optimizer state); returns how many."""
        if len(gaussians):
            self.params.append(gaussians, self.optimizer)
        return len(gaussians)

    def shape(self) -> None:
        """Let every Gaussian take its own shape from now on: three scales and a rotation, both
        optimised (`prune.shape`; the map renders as before until the next step). Gaussians
        added later start round, with three equal scales."""
        self.params.widen(self.optimizer)
        self._open_rotations()

    def _open_rotations(self) -> None:
        """Optimise the rotations too (at `mapping.lr_quats`), unless they already are."""
        if all(group.get("name") != "quats" for group in self.optimizer.param_groups):
            lr = self.config.mapping.lr_quats
            self.optimizer.param_groups.append(
                {"params": [self.params.quats], "lr": lr, "name": "quats"}
            )

    def keep(self, index: torch.Tensor) -> int:
        """Keep the Gaussians at `index` (bool mask or indices); returns how many were removed."""
        before = len(self.params)
        self.params.keep(index, self.optimizer)
        return before - len(self.params)

    def cleanup(self, huge: bool = True) -> int:
        """Remove Gaussians with opacity < alpha_min (and, with `huge`, a huge scale)."""
        prune = self.config.prune
        with torch.no_grad():
            opacity = torch.sigmoid(self.params.opacity_logits)
            drop = opacity < prune.alpha_min
            if huge and prune.huge_fraction > 0 and self.scene_radius is not None:
                largest = torch.exp(self.params.log_scales.max(dim=1).values)
                drop |= largest > prune.huge_fraction * self.scene_radius
        if not bool(drop.any()):
            return 0
        return self.keep(~drop)

    def optimize(
        self, current: View, window: list[View], iters: int, rng: np.random.Generator
    ) -> MappingStats:
        """Run `iters` mapping iterations on the current frame and its window.

        Args:
            current: the frame just tracked (its pose fixed).
            window: keyframes mapped alongside it.
            iters: iterations.
            rng: source of the per-iteration view choice.
        """
        stats = MappingStats()
        config = self.config
        every = config.prune.opacity_every
        for it in range(iters):
            if len(self.params) == 0:
                break
            use_current = it == 0 or not window or rng.random() < config.mapping.current_frame_share
            view = current if use_current else window[int(rng.integers(len(window)))]
            self._step(view, stats, None if use_current or not config.poses.window else 1.0)
            self.iterations += 1
            if every > 0 and self.iterations % every == 0:
                stats.removed += self.cleanup()
        self._check_finite()
        return stats.averaged()

    def refine(
        self,
        views: list[View],
        iters: int,
        rng: np.random.Generator,
        on_step: Callable[[float], object] | None = None,
        lr_final_fraction: float = 1.0,
        stop: Callable[[], bool] | None = None,
        row_rates: torch.Tensor | None = None,
        poses: bool = False,
    ) -> MappingStats:
        """Run `iters` mapping iterations over `views`, each view once per shuffled pass.

        Used after a pruning stage and after the last frame, so that every keyframe (not only
        the recent, overlapping ones) pulls the surviving Gaussians into the holes. These
        iterations do not advance the cyclic-cleanup count; at the end only transparent
        Gaussians are removed: the large ones are what covers the holes, and with no mapping
        left to fill the gaps, removing them cost PSNR on a pruned map (docs/design-experiments.md,
        "The final refinement").
        `on_step` is called with each iteration's total loss (`gsc merge`'s progress). The
        learning rates decay geometrically to `lr_final_fraction` of their mapping values by the
        last iteration (1: constant, as the refinements after pruning stages run; a single
        iteration runs at the full rate) and are restored after. `stop`, polled before each
        iteration, ends the refinement there when it returns true. With `poses`, the views whose
        pose is open (`View.pose`) have it stepped too, at rates decaying alike.
        """
        stats = MappingStats()
        order: list[int] = []
        base = [group["lr"] for group in self.optimizer.param_groups]
        gamma = decay_per_step(lr_final_fraction, iters)
        if row_rates is not None and row_rates.shape != (len(self.params),):
            raise ValueError(f"row_rates has shape {tuple(row_rates.shape)}, not [{len(self)}]")
        self.optimizer.row_rates = row_rates
        try:
            for k in range(iters):
                if len(self.params) == 0 or not views or (stop is not None and stop()):
                    break
                if not order:
                    order = [int(i) for i in rng.permutation(len(views))]
                for group, lr in zip(self.optimizer.param_groups, base, strict=True):
                    group["lr"] = lr * gamma**k
                view = views[order.pop()]
                self._step(view, stats, gamma**k if poses else None)
                view.release()  # (a view that can be read again: the next visit reads it)
                if on_step is not None:
                    on_step(stats.last_loss)
        finally:  # the per-frame mapping goes on at its own rates
            self.optimizer.row_rates = None
            for group, lr in zip(self.optimizer.param_groups, base, strict=True):
                group["lr"] = lr
        self._check_finite()
        if stats.iters and self.config.prune.opacity_every > 0:
            stats.removed += self.cleanup(huge=False)
        return stats.averaged()

    def loss(self, views: list[View]) -> float:
        """The mean mapping loss of the map over `views`, without a step (`gsc merge` reports
        it before and after its refinement, on the same views)."""
        with torch.no_grad():
            total = 0.0
            for view in views:
                total += float(self._terms(view).total)
                view.release()
            return total / max(len(views), 1)

    def _terms(self, view: View, T_cam_world: torch.Tensor | None = None) -> LossTerms:
        """The mapping loss terms of the map on one view (at `T_cam_world`, default its pose)."""
        view.load()
        T = view.T_cam_world() if T_cam_world is None else T_cam_world
        out = render(*self.params.render_inputs(), self.intrinsics, T, backend=self.config.backend)
        m = self.config.mapping
        edges = view.edges(m.illum_edge_sigma) if m.illum_tau > 0 else None
        return mapping_loss(out, view.color, view.depth, m, edges)

    def _check_finite(self) -> None:
        """Raise DivergenceError if a step left a NaN or an infinity in the map (the next
        step's loss would show it, but the map may be written first)."""
        bad = self.params.non_finite()
        if bad:
            raise DivergenceError("mapping", f"{', '.join(bad)} hold non-finite values", TOO_HIGH)

    def _step(self, view: View, stats: MappingStats, pose_rate: float | None = None) -> None:
        """One Adam step of the mapping loss on one view; adds its losses to `stats`. With a
        `pose_rate` and an open pose (`View.pose`), the pose steps too, at that fraction of
        its learning rates.

        Raises:
            DivergenceError: the loss is not finite (the map is not stepped).
        """
        T = view.T_cam_world()
        moves = pose_rate is not None and view.pose is not None
        T.requires_grad_(moves)
        terms = self._terms(view, T)
        value = float(terms.total.detach())
        if not math.isfinite(value):
            raise DivergenceError("mapping", f"its loss became {value}", TOO_HIGH)
        self.optimizer.zero_grad()
        terms.total.backward()
        self.optimizer.step()
        if moves and T.grad is not None:
            assert pose_rate is not None
            view.step_pose(T.grad.double().cpu().numpy(), pose_rate)
        stats.first_loss = value if stats.iters == 0 else stats.first_loss
        stats.last_loss = value
        stats.iters += 1
        stats.loss += value
        stats.color += terms.color
        stats.depth += terms.depth
        stats.illum += terms.illum
        stats.w_illum += (terms.weights or {}).get("w_illum", 0.0)
