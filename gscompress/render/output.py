"""What a render returns, and the post-processing every backend shares."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import torch

DEPTH_EPS = 1e-10
"""Floor of the silhouette when normalising depth."""


@dataclass
class RenderOutput:
    """One rendered view.

    Attributes:
        color: [H, W, 3] sum_i w_i c_i + T_final * background, with w_i = alpha_i T_i.
        depth: [H, W] sum_i w_i z_i (camera z, not normalised).
        depth_normalized: [H, W] depth / max(silhouette, 1e-10): the expected depth.
        silhouette: [H, W] sum_i w_i = 1 - T_final (accumulated opacity).
        contribution: [N] sum over pixels of alpha_i T_i (no gradient), or None when not asked.
        backend: the backend that produced this output ("torch", "cpu" or "gsplat").
        radii_of: computes `radii` when first read (gsplat projects again for them, so that
            renders nobody asks about visibility, tracking and mapping ones, do not pay).
    """

    color: torch.Tensor
    depth: torch.Tensor
    depth_normalized: torch.Tensor
    silhouette: torch.Tensor
    contribution: torch.Tensor | None
    backend: str
    radii_of: Callable[[], torch.Tensor] = field(repr=False, compare=False)

    @cached_property
    def radii(self) -> torch.Tensor:
        """[N] int32 3-sigma screen radius in pixels, the same rule on every backend; 0 for a
        Gaussian that touches no tile of the image."""
        return self.radii_of()

    @property
    def visible(self) -> torch.Tensor:
        """[N] bool: the Gaussians that touch at least one tile of the image."""
        return self.radii > 0


def finish_output(
    color: torch.Tensor,
    depth: torch.Tensor,
    T_final: torch.Tensor,
    radii_of: Callable[[], torch.Tensor],
    contribution: torch.Tensor | None,
    background: torch.Tensor | None,
    backend: str,
) -> RenderOutput:
    """Assemble a RenderOutput from composited colour [H, W, 3], depth and T_final [H, W]."""
    silhouette = 1.0 - T_final  # [H, W]
    if background is not None:
        color = color + T_final[..., None] * background  # [H, W, 3]
    return RenderOutput(
        color=color,
        depth=depth,
        depth_normalized=depth / torch.clamp(silhouette, min=DEPTH_EPS),
        silhouette=silhouette,
        contribution=contribution,
        backend=backend,
        radii_of=radii_of,
    )
