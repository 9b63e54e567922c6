"""GaussianMap: the one data structure for a 3D Gaussian Splatting map.

Parameters are stored raw (pre-activation), as 3DGS PLY files store them: log scales, opacity
logits, unnormalised (w, x, y, z) quaternions and colour as spherical-harmonic coefficients.
Each Gaussian carries a stable uint32 id and the running sums from which its PWAS importance is
derived, so that scores survive pruning, sharing and merging.

The class is numpy-backed and imports torch only in `to_tensors` / `from_tensors`, so the offline
commands (info, prune, share, export-ply) never load torch.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from gscompress.camera import quat_to_rotmat
from gscompress.errors import MapError

if TYPE_CHECKING:
    import torch

SH_C0 = 0.28209479177387814
"""Zeroth-order real spherical-harmonic constant: rgb = 0.5 + SH_C0 * f_dc."""

PWAS_EPS = 1e-8
"""The epsilon of the PWAS score S / (W + eps) (paper Eq. 8)."""

MAX_ABS_LOG_SCALE = 40.0
"""Largest |log scale| a map may hold: e^40 m (and e^-40) keeps every covariance and its
inverse finite in float32 (a real map's scales, micrometres to metres, lie far inside)."""

SH_REST_COUNTS = {0: 0, 1: 3, 2: 8, 3: 15}
"""Higher-order SH coefficients per colour channel for each SH degree."""

_FLOAT_FIELDS = (
    "means",
    "log_scales",
    "quats",
    "opacity_logits",
    "sh_dc",
    "sh_rest",
    "importance_sum",
    "importance_weight",
    "alpha_t_sum",
)

_STORED_AS = {
    "means": "x y z",
    "log_scales": "scale_*",
    "quats": "rot_0..3",
    "opacity_logits": "opacity",
    "sh_dc": "f_dc_*",
    "sh_rest": "f_rest_*",
}
"""The PLY and `/gaussians` fields each array is stored as, for messages about a file's map."""


def _named(name: str) -> str:
    """A field for a message: its name here and, where it differs, as files store it."""
    return f"{name} ({_STORED_AS[name]})" if name in _STORED_AS else name


def _own(array: Any, dtype: type[np.generic]) -> np.ndarray:
    """`array` as a contiguous, writable array of `dtype` (a copy when it was a read-only view,
    such as a field of a file's buffer that needed no conversion: one row, or none). A float
    beyond `dtype`'s range becomes inf quietly: `validate` refuses it with a message."""
    with np.errstate(over="ignore"):
        out = np.ascontiguousarray(array, dtype=dtype)
    return out if out.flags.writeable else out.copy()


@dataclass(eq=False)
class GaussianMap:
    """A set of N 3D Gaussians with raw parameters, ids and importance sums.

    Attributes:
        means: [N, 3] float32 centres in world coordinates (metres).
        log_scales: [N, 1] (isotropic) or [N, 3] float32 natural-log standard deviations.
        quats: [N, 4] float32 unnormalised rotations (w, x, y, z).
        opacity_logits: [N] float32 opacities before the sigmoid.
        sh_dc: [N, 3] float32 zeroth-order SH colour (`f_dc`).
        sh_rest: [N, K, 3] float32 higher-order SH, K in {0, 3, 8, 15}.
        ids: [N] uint32 stable identifiers, unique within a map.
        importance_sum: [N] float32 PWAS numerator S_i = sum_t w_i^t I_i^t.
        importance_weight: [N] float32 PWAS denominator W_i = sum_t w_i^t (0: never scored).
        alpha_t_sum: [N] float32 unweighted sum_t I_i^t (the alpha*T-sum baseline score).
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    ids: np.ndarray
    importance_sum: np.ndarray
    importance_weight: np.ndarray
    alpha_t_sum: np.ndarray

    def __post_init__(self) -> None:
        for name in _FLOAT_FIELDS:
            setattr(self, name, _own(getattr(self, name), np.float32))
        self.ids = _own(self.ids, np.uint32)
        self._check_shapes()

    @classmethod
    def new(
        cls,
        means: Any,
        log_scales: Any,
        quats: Any,
        opacity_logits: Any,
        sh_dc: Any,
        sh_rest: Any = None,
        ids: Any = None,
        importance_sum: Any = None,
        importance_weight: Any = None,
        alpha_t_sum: Any = None,
    ) -> GaussianMap:
        """Build a map, filling optional fields: no higher SH, ids 0..N-1, zero importance."""
        n = int(np.shape(means)[0])
        zeros = np.zeros(n, dtype=np.float32)
        return cls(
            means=means,
            log_scales=log_scales,
            quats=quats,
            opacity_logits=opacity_logits,
            sh_dc=sh_dc,
            sh_rest=np.zeros((n, 0, 3), np.float32) if sh_rest is None else sh_rest,
            ids=np.arange(n, dtype=np.uint32) if ids is None else ids,
            importance_sum=zeros if importance_sum is None else importance_sum,
            importance_weight=zeros if importance_weight is None else importance_weight,
            alpha_t_sum=zeros if alpha_t_sum is None else alpha_t_sum,
        )

    @classmethod
    def empty(cls, isotropic: bool = True, sh_degree: int = 0) -> GaussianMap:
        """A map with no Gaussians."""
        k = SH_REST_COUNTS[sh_degree]
        return cls.new(
            np.zeros((0, 3)),
            np.zeros((0, 1 if isotropic else 3)),
            np.zeros((0, 4)),
            np.zeros(0),
            np.zeros((0, 3)),
            sh_rest=np.zeros((0, k, 3)),
        )

    # ------------------------------------------------------------------ structure

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def __repr__(self) -> str:
        kind = "isotropic" if self.isotropic else "anisotropic"
        return f"GaussianMap(n={len(self)}, {kind}, sh_degree={self.sh_degree})"

    @property
    def isotropic(self) -> bool:
        """True when every Gaussian has one scale for all three axes."""
        return self.log_scales.shape[1] == 1

    @property
    def sh_degree(self) -> int:
        """Spherical-harmonic degree of the colour (0: view-independent)."""
        k = self.sh_rest.shape[1]
        return next(d for d, c in SH_REST_COUNTS.items() if c == k)

    @property
    def has_importance(self) -> bool:
        """True when at least one Gaussian has been scored (a non-zero PWAS weight)."""
        return bool(np.any(self.importance_weight > 0))

    @property
    def importance(self) -> np.ndarray:
        """[N] float32 PWAS score S / (W + eps) (paper Eq. 8); 0 for unscored Gaussians."""
        return (self.importance_sum / (self.importance_weight + np.float32(PWAS_EPS))).astype(
            np.float32
        )

    def _check_shapes(self) -> None:
        n = len(self)
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
            "sh_dc": (n, 3),
            "ids": (n,),
            "importance_sum": (n,),
            "importance_weight": (n,),
            "alpha_t_sum": (n,),
        }
        for name, shape in expected.items():
            got = getattr(self, name).shape
            if got != shape:
                raise MapError(f"{name} has shape {got}, expected {shape}")
        if self.log_scales.ndim != 2 or self.log_scales.shape not in ((n, 1), (n, 3)):
            raise MapError(f"log_scales has shape {self.log_scales.shape}, expected ({n}, 1|3)")
        if self.sh_rest.ndim != 3 or self.sh_rest.shape[0] != n or self.sh_rest.shape[2] != 3:
            raise MapError(f"sh_rest has shape {self.sh_rest.shape}, expected ({n}, K, 3)")
        if self.sh_rest.shape[1] not in SH_REST_COUNTS.values():
            raise MapError(f"sh_rest has {self.sh_rest.shape[1]} coefficients per channel")

    def validate(self) -> GaussianMap:
        """Check finiteness, id uniqueness and sign of the importance sums, and that what
        rendering and ranking derive from the raw values stays finite: scales within
        e^+-`MAX_ABS_LOG_SCALE`, rotations whose squared length float32 holds, finite scores.

        Returns:
            self, so that calls can be chained.

        Raises:
            MapError: naming the first problem found.
        """
        self._check_shapes()
        for name in _FLOAT_FIELDS:
            values = getattr(self, name)
            if not np.isfinite(values).all():
                bad = int(np.count_nonzero(~np.isfinite(values)))
                raise MapError(f"{_named(name)} has {bad} non-finite value(s)")
        for name in ("importance_sum", "importance_weight", "alpha_t_sum"):
            if np.any(getattr(self, name) < 0):
                raise MapError(f"{name} has negative values")
        if _has_duplicates(self.ids):
            raise MapError("ids are not unique")
        if len(self) and np.any(np.all(self.quats == 0, axis=1)):
            raise MapError(f"{_named('quats')} has all-zero rotations")
        if np.any(np.abs(self.log_scales) > MAX_ABS_LOG_SCALE):
            raise MapError(
                f"{_named('log_scales')} has values beyond +-{MAX_ABS_LOG_SCALE:g} (scales of e^40)"
            )
        squared = np.square(self.quats, dtype=np.float64).sum(axis=1)
        if np.any(squared > np.finfo(np.float32).max):
            raise MapError(f"{_named('quats')} has rotations too long to normalise in float32")
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            scores = self.importance
        if not np.isfinite(scores).all():
            raise MapError("importance_sum / importance_weight (the PWAS score) overflows")
        return self

    # ------------------------------------------------------------------ subsets

    def select(self, index: np.ndarray | slice | Sequence[int]) -> GaussianMap:
        """A new map with the Gaussians at `index` (integer indices, boolean mask or slice)."""
        if not isinstance(index, slice):
            index = np.asarray(index)
            if index.dtype == bool and index.shape != (len(self),):
                raise MapError(f"mask has shape {index.shape}, expected ({len(self)},)")
        return GaussianMap(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @staticmethod
    def concat(maps: Sequence[GaussianMap]) -> GaussianMap:
        """Concatenate maps (all fields, ids and importance sums).

        An isotropic map concatenated with an anisotropic one is promoted to three scales.

        Raises:
            MapError: for an empty list, mismatched SH degrees or duplicate ids.
        """
        if not maps:
            raise MapError("nothing to concatenate")
        degrees = {m.sh_degree for m in maps}
        if len(degrees) > 1:
            raise MapError(f"cannot concatenate maps of SH degrees {sorted(degrees)}")
        anisotropic = any(not m.isotropic for m in maps)
        parts = [m.as_anisotropic() if anisotropic else m for m in maps]
        out = GaussianMap(
            **{f.name: np.concatenate([getattr(m, f.name) for m in parts]) for f in fields(maps[0])}
        )
        if _has_duplicates(out.ids):
            raise MapError("concatenated maps share Gaussian ids; renumber one of them first")
        return out

    def as_anisotropic(self) -> GaussianMap:
        """The same map with three log-scales per Gaussian."""
        if not self.isotropic:
            return self
        return replace(self, log_scales=np.repeat(self.log_scales, 3, axis=1))

    def with_importance(
        self,
        importance_sum: np.ndarray,
        importance_weight: np.ndarray,
        alpha_t_sum: np.ndarray | None = None,
    ) -> GaussianMap:
        """A copy with new importance sums (and optionally a new alpha*T sum)."""
        return replace(
            self,
            importance_sum=importance_sum,
            importance_weight=importance_weight,
            alpha_t_sum=self.alpha_t_sum if alpha_t_sum is None else alpha_t_sum,
        )

    def equals(self, other: GaussianMap) -> bool:
        """True when every field of both maps is bit-identical (same dtype, shape and bytes)."""
        return all(
            getattr(self, f.name).shape == getattr(other, f.name).shape
            and getattr(self, f.name).tobytes() == getattr(other, f.name).tobytes()
            for f in fields(self)
        )

    # ------------------------------------------------------------------ activations

    def scales(self) -> np.ndarray:
        """[N, 3] float32 standard deviations in metres."""
        return np.broadcast_to(np.exp(self.log_scales), (len(self), 3)).astype(np.float32)

    def opacities(self) -> np.ndarray:
        """[N] float32 opacities in (0, 1)."""
        return (1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))).astype(np.float32)

    def rotations(self) -> np.ndarray:
        """[N, 4] float32 unit quaternions (w, x, y, z)."""
        norm = np.linalg.norm(self.quats, axis=1, keepdims=True)
        return (self.quats / np.maximum(norm, np.float32(1e-12))).astype(np.float32)

    def covariances(self) -> np.ndarray:
        """[N, 3, 3] float64 world covariances R diag(s^2) R^T (s^2 I for an isotropic map,
        which no rotation changes)."""
        variances = np.square(self.scales().astype(np.float64))
        if self.isotropic:
            return variances[:, :, None] * np.eye(3)
        R = quat_to_rotmat(self.quats)
        return np.matmul(R * variances[:, None, :], R.transpose(0, 2, 1))

    def colors(self) -> np.ndarray:
        """[N, 3] float32 view-independent RGB from the SH DC term, clipped to [0, 1]."""
        return np.clip(0.5 + SH_C0 * self.sh_dc, 0.0, 1.0).astype(np.float32)

    # ------------------------------------------------------------------ torch

    def to_tensors(
        self, device: str | torch.device = "cpu", dtype: torch.dtype | None = None
    ) -> dict[str, torch.Tensor]:
        """Every field as a torch tensor (float fields in `dtype`, default float32; ids int64)."""
        import torch

        float_dtype = dtype or torch.float32
        out = {
            name: torch.from_numpy(getattr(self, name)).to(device=device, dtype=float_dtype)
            for name in _FLOAT_FIELDS
        }
        out["ids"] = torch.from_numpy(self.ids.astype(np.int64)).to(device)
        return out

    @classmethod
    def from_tensors(cls, tensors: Mapping[str, Any]) -> GaussianMap:
        """Inverse of `to_tensors` (detaches, moves to CPU, casts to float32 / uint32)."""
        arrays = {}
        for f in fields(cls):
            value = tensors[f.name]
            if hasattr(value, "detach"):
                value = value.detach().cpu().numpy()
            arrays[f.name] = value
        return cls(**arrays)


def _has_duplicates(ids: np.ndarray) -> bool:
    """True when some id occurs twice (a sort: much faster than np.unique's hashing here;
    none when they ascend already, as a map's ids mostly do)."""
    if np.all(ids[1:] > ids[:-1]):
        return False
    ordered = np.sort(ids)
    return bool(np.any(ordered[1:] == ordered[:-1]))


def random_map(
    n: int,
    seed: int = 0,
    isotropic: bool = True,
    sh_degree: int = 0,
    scored: bool = True,
    extent: float = 2.0,
) -> GaussianMap:
    """A reproducible random map, for tests, examples and benchmarks.

    Args:
        n: number of Gaussians.
        seed: random seed.
        isotropic: one scale per Gaussian instead of three.
        sh_degree: SH degree of the colour.
        scored: fill the importance sums with positive values.
        extent: half-width of the cube the means are drawn from (metres).
    """
    rng = np.random.default_rng(seed)
    k = SH_REST_COUNTS[sh_degree]
    zeros = np.zeros(n, np.float32)
    return GaussianMap(
        means=rng.uniform(-extent, extent, (n, 3)),
        log_scales=rng.uniform(-5.0, -2.0, (n, 1 if isotropic else 3)),
        quats=rng.normal(size=(n, 4)) + np.array([3.0, 0, 0, 0]),
        opacity_logits=rng.normal(0.0, 2.0, n),
        sh_dc=(rng.uniform(0.0, 1.0, (n, 3)) - 0.5) / SH_C0,  # colours in [0, 1]
        sh_rest=rng.normal(0.0, 0.1, (n, k, 3)),
        ids=rng.permutation(n).astype(np.uint32) + np.uint32(1000),
        importance_sum=rng.exponential(5.0, n) if scored else zeros,
        importance_weight=rng.uniform(0.5, 20.0, n) if scored else zeros,
        alpha_t_sum=rng.exponential(50.0, n) if scored else zeros,
    )
