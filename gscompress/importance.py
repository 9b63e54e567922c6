"""PWAS importance: proximity-weighted accumulation of alpha x transmittance (paper Eq. 6-8).

For every frame t the renderer gives each Gaussian its contribution
I_i^t = sum over pixels of alpha_i(p) T_i(p). PWAS weights it by how close the Gaussian is to
the camera centre c_t, w_i^t = exp(-||mu_i - c_t|| / sigma_d), and keeps two running sums over
the frames in which Gaussian i is visible (projected inside the image, occluded or not):

    S_i = sum_t w_i^t I_i^t,    W_i = sum_t w_i^t,    score_i = S_i / (W_i + eps).

Counting visible-but-occluded frames in W lowers the score of Gaussians that are usually hidden.
The sums (not the score) are the state: they travel with the map through logs and shares so that
accumulation can go on after a merge. The unweighted sum_t I_i^t is kept as well; it is the
alpha*T-sum baseline (LightGaussian / Mini-Splatting style) that PWAS is compared against.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from gscompress.gaussians import PWAS_EPS


@dataclass(frozen=True)
class PwasConfig:
    """PWAS hyperparameters.

    Attributes:
        sigma_d: distance scale of the proximity weight, in metres (paper default 20).
    """

    sigma_d: float = 20.0


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
        config: PwasConfig,
    ) -> None:
        """Add one frame (in place).

        Args:
            contribution: [N] I_i^t from the renderer.
            visible: [N] bool, Gaussians projected inside the image this frame.
            means: [N, 3] Gaussian centres (world).
            camera_center: [3] camera centre c_t (world).
            config: PWAS settings.
        """
        with torch.no_grad():
            dist = torch.linalg.vector_norm(means.detach().double() - camera_center.double(), dim=1)
            w = torch.exp(-dist / config.sigma_d) * visible.double()  # [N]
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
