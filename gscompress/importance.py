"""PWAS importance: proximity-weighted accumulation of alpha x transmittance (paper Eq. 6-8).

For every frame t the renderer gives each Gaussian its contribution
I_i^t = sum over pixels of alpha_i(p) T_i(p). PWAS weights it by how close the Gaussian is to
the camera centre c_t, w_i^t = exp(-||mu_i - c_t|| / sigma_d), and keeps two running sums over
the frames in which Gaussian i is visible (projected inside the image, occluded or not):

    S_i = sum_t w_i^t I_i^t,    W_i = sum_t w_i^t,    score_i = S_i / (W_i + eps).

Counting visible-but-occluded frames in W lowers the score of Gaussians that are usually hidden.

The distance scale sigma_d is scale-aware by default (`PwasConfig.sigma_d` None): the median
distance from the camera centre to the surface points of the first selected frame that has valid
depth (`median_range`), resolved once per run (`resolve_sigma_d`) so that every frame's weights
share one scale and the sums of a run stay comparable. Those points are where the first frame's
Gaussians are placed, so this is the median camera-to-Gaussian distance of the first frame. The
rule needs nothing but that frame: `gsc slam` knows it when it starts (and again when it resumes),
`gsc score` reads it from the sequence. The paper's fixed 20 m (`PAPER_SIGMA_D`) weights every
Gaussian of a room by 0.86-0.99, i.e. hardly by proximity at all; with the scene's own median
distance d_med, a Gaussian at d_med/2 weighs e^-0.5 = 0.61 and one at 2 d_med e^-2 = 0.14.
sigma_d = inf turns the proximity weight off (w = 1), the ablation of PWAS without it.
The sums (not the score) are the state: they travel with the map through logs and shares so that
accumulation can go on after a merge. The unweighted sum_t I_i^t is kept as well; it is the
alpha*T-sum baseline (LightGaussian / Mini-Splatting style) that PWAS is compared against.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch

from gscompress.camera import Intrinsics
from gscompress.errors import InputError
from gscompress.gaussians import PWAS_EPS

PAPER_SIGMA_D = 20.0
"""The paper's fixed sigma_d, metres."""


@dataclass(frozen=True)
class PwasConfig:
    """PWAS hyperparameters.

    Attributes:
        sigma_d: distance scale of the proximity weight, in metres; None (the default, `auto`
            on the command line and in YAML, or null): scale-aware, the median camera-to-surface
            distance of the run's first frame with valid depth (`median_range`; module
            docstring); `math.inf` (`inf` in YAML and on the command line): no proximity
            weighting (every visible frame weighs 1). The paper used 20.
        final_scores: when a run has mapped all its frames, its finished map is scored again
            from every pose of the run (`gscompress.ops.score.score_map`, the run's sigma_d),
            and the final map is logged with those sums instead of the ones accumulated while
            the map grew (the pruning stages still rank by those). A run that received a share
            (`gsc slam --inject`) keeps its accumulated sums: they hold the sender's views.
            docs/pwas.md, "The finished map's sums".
    """

    sigma_d: float | None = None
    final_scores: bool = True


def median_range(depth: np.ndarray, intrinsics: Intrinsics) -> float | None:
    """Median distance (m) from the camera centre to the back-projected points of the pixels with
    valid depth (> 0) of one [H, W] depth map; None when no pixel has valid depth.

    Each pixel (u, v) at depth z lies at distance z * sqrt(((u - cx) / fx)^2 + ((v - cy) / fy)^2
    + 1) from the camera (pixel centres at integer coordinates, as `Intrinsics.backproject`).
    """
    depth = np.asarray(depth, dtype=np.float64)
    v, u = np.nonzero(depth > 0)
    if len(u) == 0:
        return None
    points = intrinsics.backproject(u, v, depth[v, u], np.eye(4))
    return float(np.median(np.linalg.norm(points, axis=1)))


def resolve_sigma_d(
    sigma_d: float | None, depths: Iterable[np.ndarray], intrinsics: Intrinsics
) -> float:
    """The sigma_d (m) a run uses: `sigma_d` itself when given (a positive number or inf), else
    `median_range` of the first of `depths` (in frame order) that has valid depth.

    Raises:
        InputError: sigma_d not above 0, or None and no depth map has a valid pixel.
    """
    if sigma_d is not None:
        if not sigma_d > 0:  # (nan too)
            raise InputError(f"sigma_d must be above 0 (or inf), got {sigma_d}")
        return float(sigma_d)
    for depth in depths:
        found = median_range(depth, intrinsics)
        if found is not None and found > 0:
            return found
    raise InputError("no frame has valid depth: cannot derive sigma_d from the scene; set it")


def sigma_d_value(sigma_d: float | None) -> float | str | None:
    """sigma_d as JSON holds it: a number, "inf" (no proximity weighting) or None (auto)."""
    if sigma_d is not None and math.isinf(sigma_d):
        return "inf"
    return sigma_d


@dataclass
class ImportanceSums:
    """The running PWAS state of N Gaussians (tensors on the map's device).

    Attributes:
        importance_sum: [N] S_i = sum_t w_i^t I_i^t.
        importance_weight: [N] W_i = sum_t w_i^t over frames where i is visible.
        alpha_t_sum: [N] sum_t I_i^t.
    """

    importance_sum: torch.Tensor
    importance_weight: torch.Tensor
    alpha_t_sum: torch.Tensor

    @classmethod
    def zeros(cls, n: int, device: str | torch.device = "cpu") -> ImportanceSums:
        """Sums for n Gaussians that have never been scored."""
        z = torch.zeros(n, dtype=torch.float64, device=device)
        return cls(z.clone(), z.clone(), z.clone())

    def __len__(self) -> int:
        return int(self.importance_sum.shape[0])

    def accumulate(
        self,
        contribution: torch.Tensor,
        visible: torch.Tensor,
        means: torch.Tensor,
        camera_center: torch.Tensor,
        sigma_d: float,
    ) -> None:
        """Add one frame (in place).

        Args:
            contribution: [N] I_i^t from the renderer.
            visible: [N] bool, Gaussians projected inside the image this frame.
            means: [N, 3] Gaussian centres (world).
            camera_center: [3] camera centre c_t (world).
            sigma_d: distance scale of the proximity weight, metres (resolved: a positive
                number, or inf for none).
        """
        with torch.no_grad():
            dist = torch.linalg.vector_norm(means.detach().double() - camera_center.double(), dim=1)
            w = torch.exp(-dist / sigma_d) * visible.double()  # [N] (exp(-0) = 1 at inf)
            contribution = contribution.detach().double()
            self.importance_sum += w * contribution
            self.importance_weight += w
            self.alpha_t_sum += contribution

    def score(self) -> torch.Tensor:
        """[N] PWAS score S / (W + eps), as `GaussianMap.importance` computes it from the sums."""
        return self.importance_sum / (self.importance_weight + PWAS_EPS)

    def select(self, index: torch.Tensor) -> ImportanceSums:
        """The sums of the Gaussians at `index` (mask or indices), e.g. after pruning."""
        return ImportanceSums(
            self.importance_sum[index], self.importance_weight[index], self.alpha_t_sum[index]
        )

    def extend(self, other: ImportanceSums) -> ImportanceSums:
        """These sums followed by `other`'s (new or injected Gaussians)."""
        return ImportanceSums(
            torch.cat([self.importance_sum, other.importance_sum]),
            torch.cat([self.importance_weight, other.importance_weight]),
            torch.cat([self.alpha_t_sum, other.alpha_t_sum]),
        )
