"""Folding the Gaussians a prune or a share drops into the ones it keeps.

Dropping 70% of a map leaves holes where the dropped Gaussians drew surface. Folding keeps the
same kept Gaussians (same count, ids and order) but lets each stand for the dropped ones around
it: every dropped Gaussian joins its nearest kept one (by centre) when their centres lie within
`FOLD_REACH` times the sum of their mean scales, and each kept Gaussian becomes the moment-matched
Gaussian of its group (`moment_match`): the weighted mean of the centres, the weighted
covariance of the group about it, the weighted colour, with weights `fold_weights` (opacity
times mean scale squared: how much of a view a Gaussian covers), and the group's largest
opacity. A dropped Gaussian farther than that from every kept one is dropped as before. The
folded Gaussian draws what its group drew, so its PWAS numerator and alpha*T sum are the group's
sums, over the kept Gaussian's own visibility weight: its score (Eq. 8) is at least what it was,
and a prune or share still keeps the highest scores.

Measured on tabletop's unpruned map (11052 Gaussians, `--keep 0.3`, PSNR off the keyframes):
dropping gives 15.75 dB, folding 19.54; reach 1 gave 16.96, 3 19.29, 4 19.54, none (every
dropped Gaussian folded) 19.11; the group's weighted opacity 18.65 and its union 17.51 against
its largest; weights of opacity times scale^0 or ^3 18.36 and 18.92 (docs/prune-refine.md).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from gscompress.camera import rotmat_to_quat
from gscompress.gaussians import GaussianMap
from gscompress.threads import cpu_threads

FOLD_REACH = 4.0
"""A dropped Gaussian folds into its nearest kept one when their centres lie within this many
times the sum of their mean scales."""

LOGIT_BOUND = 1e-6
"""Opacities are kept within [bound, 1 - bound] before taking their logit."""


def mean_scales(gaussians: GaussianMap) -> np.ndarray:
    """[N] float64 mean of each Gaussian's three standard deviations (metres)."""
    return gaussians.scales().astype(np.float64).mean(axis=1)


def fold_weights(gaussians: GaussianMap) -> np.ndarray:
    """[N] float64 weight of each Gaussian in a fold: opacity x (mean scale)^2."""
    return gaussians.opacities().astype(np.float64) * np.square(mean_scales(gaussians))


def fold_groups(gaussians: GaussianMap, kept: np.ndarray, reach: float = FOLD_REACH) -> np.ndarray:
    """[N] int64: for each Gaussian, the position in `kept` of the kept Gaussian it folds into
    (a kept one into itself), or -1 for a dropped one too far from every kept one."""
    kept = np.asarray(kept, dtype=np.int64)
    group = np.full(len(gaussians), -1, dtype=np.int64)
    group[kept] = np.arange(len(kept))
    dropped = np.flatnonzero(group < 0)
    if len(dropped) == 0 or len(kept) == 0:
        return group
    means = gaussians.means.astype(np.float64)
    scale = mean_scales(gaussians)
    distance, nearest = cKDTree(means[kept]).query(means[dropped], workers=cpu_threads())
    near = distance <= reach * (scale[kept][nearest] + scale[dropped])
    group[dropped[near]] = nearest[near]
    return group


def moment_match(
    weights: np.ndarray, means: np.ndarray, covariances: np.ndarray, group: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian each of `k` groups stands for, matching its first two moments.

    mu_g = sum_i w_i mu_i / W_g and Sigma_g = sum_i w_i (Sigma_i + (mu_i - mu_g)(mu_i - mu_g)^T)
    / W_g over the members i of group g (W_g = sum_i w_i).

    Args:
        weights: [N] positive weights.
        means: [N, 3] centres.
        covariances: [N, 3, 3] covariances.
        group: [N] group of each Gaussian in [0, k) (every group has a member).
        k: number of groups.

    Returns:
        ([k, 3] means, [k, 3, 3] covariances), float64.
    """
    total = np.bincount(group, weights, k)
    moment = np.stack([np.bincount(group, weights * means[:, c], k) for c in range(3)], 1)
    mean: np.ndarray = moment / total[:, None]
    offset = means - mean[group]
    spread = covariances + offset[:, :, None] * offset[:, None, :]
    cov = group_sums(weights[:, None, None] * spread, group, k)
    return mean, cov / total[:, None, None]


def group_sums(values: np.ndarray, group: np.ndarray, k: int) -> np.ndarray:
    """[k, ...] float64 sums of `values` [N, ...] over each of `k` groups (one bincount per
    component: many times faster than np.add.at)."""
    flat = values.reshape(len(values), -1).astype(np.float64)
    sums = [np.bincount(group, flat[:, j], k) for j in range(flat.shape[1])]
    return np.stack(sums, 1).reshape((k, *values.shape[1:])) if sums else np.zeros((k, 0))


def group_mean(values: np.ndarray, weights: np.ndarray, group: np.ndarray, k: int) -> np.ndarray:
    """[k, ...] weighted mean of `values` [N, ...] over each of `k` groups."""
    flat = values.reshape(len(values), -1).astype(np.float64)
    sums = group_sums(weights[:, None] * flat, group, k)
    return (sums / np.bincount(group, weights, k)[:, None]).reshape((k, *values.shape[1:]))


def fold(gaussians: GaussianMap, kept: np.ndarray, reach: float = FOLD_REACH) -> GaussianMap:
    """The Gaussians at positions `kept`, each moment-matched to itself and the dropped ones
    that fold into it (module docstring). Same count, order and ids as `gaussians.select(kept)`;
    an isotropic map stays isotropic (the isotropic Gaussian of the same trace)."""
    kept = np.asarray(kept, dtype=np.int64)
    k = len(kept)
    group = fold_groups(gaussians, kept, reach)
    members = np.flatnonzero(group >= 0)
    g = group[members]
    if len(members) == k:  # (nothing folds: the kept Gaussians as they are)
        return gaussians.select(kept)
    src = gaussians.select(members)
    weights = np.maximum(fold_weights(src), np.finfo(np.float64).tiny)
    mean, cov = moment_match(weights, src.means.astype(np.float64), src.covariances(), g, k)
    opacity = np.zeros(k)
    np.maximum.at(opacity, g, src.opacities().astype(np.float64))
    opacity = np.clip(opacity, LOGIT_BOUND, 1.0 - LOGIT_BOUND)
    if gaussians.isotropic:
        log_scales = 0.5 * np.log(np.trace(cov, axis1=1, axis2=2) / 3.0)[:, None]
        quats = gaussians.quats[kept]
    else:
        variances, axes = np.linalg.eigh(cov)
        axes[np.linalg.det(axes) < 0, :, 2] *= -1.0  # (a rotation, not a reflection)
        log_scales = 0.5 * np.log(np.maximum(variances, np.finfo(np.float32).tiny))
        quats = rotmat_to_quat(axes)

    def added(values: np.ndarray) -> np.ndarray:
        return np.bincount(g, values.astype(np.float64), k)

    base = gaussians.select(kept)
    return replace(
        base,
        means=mean.astype(np.float32),
        log_scales=log_scales.astype(np.float32),
        quats=np.asarray(quats, dtype=np.float32),
        opacity_logits=np.log(opacity / (1.0 - opacity)).astype(np.float32),
        sh_dc=group_mean(src.sh_dc, weights, g, k).astype(np.float32),
        sh_rest=group_mean(src.sh_rest, weights, g, k).astype(np.float32),
        importance_sum=added(src.importance_sum),
        alpha_t_sum=added(src.alpha_t_sum),
    ).validate()
