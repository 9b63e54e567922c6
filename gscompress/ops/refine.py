"""Refining a finished map on fixed views with a fresh optimizer.

`gsc merge` refines the merged map on the receiver's views; `gsc prune --refine` and `gsc share
--refine` refine the Gaussians they kept on the log's keyframes. Both run the SLAM mapper's
iterations (`gscompress.slam.mapper`, the mapping loss and learning rates of the log's config)
at poses that stay fixed, without the cyclic removal: no Gaussian is added or dropped, so a
refined map has the same Gaussians, ids and order as the one given, and a Gaussian whose
opacity collapses stays (a prune keeps the count it was asked for). The learning rates may
decay over the refinement. PWAS sums are carried, not added to.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

from gscompress.camera import Intrinsics
from gscompress.errors import DivergenceError, MapError
from gscompress.gaussians import GaussianMap
from gscompress.seeds import seeded_rng


class MapRefiner(Protocol):
    """Refines a map on the frames of the log it came from
    (`gscompress.pipeline.refining.LogRefiner`, which needs torch: prune and share take one only
    when asked to refine)."""

    def __call__(
        self,
        gaussians: GaussianMap,
        rates: Any = None,
        teacher: GaussianMap | None = None,
        iters: int | None = None,
    ) -> tuple[GaussianMap, dict[str, Any]]:
        """The map refined (same Gaussians, same order) and the refinement's statistics;
        `teacher`, the map it was cut from, is also rendered between the keyframes and refined
        on (`gscompress.pipeline.refining.PSEUDO_VIEWS`); `iters` (None: its own) iterations."""
        ...

    def record(self) -> dict[str, Any]:
        """What a provenance step records of the refinement."""
        ...

    @property
    def anisotropic(self) -> bool:
        """Whether it refines three scales and a rotation per Gaussian (`cut_pool`)."""
        ...


def refine(
    gaussians: GaussianMap,
    views: Sequence[Any],
    intrinsics: Intrinsics,
    config: Any,
    iters: int,
    *,
    device: Any = "cpu",
    seed: int = 0,
    lr_final_fraction: float = 1.0,
    progress: Callable[[int], object] | None = None,
    instead: str = "merge with `iters` 0 to concatenate only",
    rates: Any = None,
) -> tuple[GaussianMap, dict[str, Any]]:
    """Optimise a map on fixed views for `iters` iterations, each view once per shuffled pass.

    Args:
        gaussians: the map (SH degree 0: the SLAM parameterisation).
        views: `gscompress.slam.keyframes.View` objects (observed colour, depth and pose).
        intrinsics: camera intrinsics at the views' size.
        config: a `SlamConfig` (mapping loss and learning rates are taken from it).
        iters: iterations.
        device: torch device of the views.
        seed: seed of the view order.
        lr_final_fraction: the learning rates (the config's mapping ones) decay geometrically
            to this fraction of their value at the last iteration (1: constant).
        progress: called with 1 after each iteration.
        instead: what to do without a refinement, said when it diverges (it may name the
            parameter `iters`, as `GscError`'s do).
        rates: [N] factors in [0, 1] on each Gaussian's steps (0: it keeps its values; None: 1
            for every Gaussian). A merge slows the share's Gaussians that the receiver's views
            barely see.

    Returns:
        The refined map (same Gaussians, same order, same ids and sums) and
        {"iters", "loss_before", "loss_after"}: the mean mapping loss over all the views
        before and after the refinement.

    Raises:
        MapError: a map with higher SH bands (they would be dropped), or no views.
        InputError: a negative seed.
        DivergenceError: the refinement's loss or the map stopped being finite.
    """
    import torch

    from gscompress.slam.mapper import Mapper

    rng = seeded_rng(seed)
    if iters <= 0 or len(gaussians) == 0:
        return gaussians, {"iters": 0}
    if gaussians.sh_degree > 0:
        raise MapError(
            f"refinement optimises SH degree 0 only; this map has degree {gaussians.sh_degree} "
            f"({instead} and keep its higher bands)",
            options=("iters",),
        )
    if not views:
        raise MapError("no views to refine on")
    config = config.with_overrides(**{"prune.opacity_every": 0, "isotropic": gaussians.isotropic})
    mapper = Mapper(config, intrinsics, torch.device(device))
    mapper.add(gaussians)
    views = list(views)
    loss_before = mapper.loss(views)
    on_step = None if progress is None else lambda _: progress(1)
    try:
        mapper.refine(
            views,
            iters,
            rng,
            on_step=on_step,
            lr_final_fraction=lr_final_fraction,
            row_rates=None
            if rates is None
            else torch.as_tensor(rates, dtype=torch.float32, device=mapper.device),
        )
    except DivergenceError as exc:  # (its rates are the log's mapping ones, from its config)
        raise DivergenceError(
            "the refinement",
            exc.detail,
            f"it ran at the log's mapping rates; {instead}",
            options=("iters",),
        ) from None
    stats = {"iters": iters, "loss_before": loss_before, "loss_after": mapper.loss(views)}
    return mapper.params.to_map(), stats


def refined(
    gaussians: GaussianMap,
    results: dict[str, Any],
    refine: MapRefiner | None,
    teacher: GaussianMap | None = None,
) -> tuple[GaussianMap, dict[str, Any]]:
    """`gaussians` through `refine` when there is one (with `teacher`, the map they were cut
    from), its statistics added to `results` as `refine_*`."""
    if refine is None:
        return gaussians, results
    gaussians, stats = refine(gaussians, teacher=teacher)
    return gaussians, {**results, **{f"refine_{k}": v for k, v in stats.items()}}
