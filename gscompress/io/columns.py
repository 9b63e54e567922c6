"""Named per-Gaussian columns: the one mapping between GaussianMap and packed records.

Both file formats (the MCAP `/gaussians` PointCloud and 3DGS PLY) store a map as records of
named scalar fields, with the 3DGS PLY names: x y z, scale_0..2 (log), rot_0..3 (w x y z),
opacity (logit), f_dc_0..2, f_rest_* (channel-major, as the INRIA PLY writer lays them out),
plus our own importance, importance_sum, importance_weight, alpha_t_sum and id. This module turns
a map into such columns and back, and packs / unpacks columns as little-endian records.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from gscompress.errors import MapError
from gscompress.gaussians import SH_REST_COUNTS, GaussianMap

GEOMETRY = ("x", "y", "z", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
"""Required columns for position, shape and orientation."""

APPEARANCE = ("opacity", "f_dc_0", "f_dc_1", "f_dc_2")
"""Required columns for opacity and base colour."""

REQUIRED = GEOMETRY + APPEARANCE

IMPORTANCE = ("importance", "importance_sum", "importance_weight", "alpha_t_sum")
"""Optional score columns (the score `importance` is derived; the sums are the state)."""


def f_rest_names(coefficients: int) -> tuple[str, ...]:
    """Column names of `coefficients` higher-order SH values per colour channel."""
    return tuple(f"f_rest_{i}" for i in range(3 * coefficients))


def map_to_columns(gaussians: GaussianMap, importance: bool = True) -> dict[str, np.ndarray]:
    """Columns of a map, in storage order: geometry, appearance, f_rest, [importance], id.

    Isotropic maps repeat their one log-scale in scale_0..2 (what 3DGS tools expect).

    Returns:
        name -> [N] array (float32, id uint32); arrays may be views of the map's.
    """
    scales = np.broadcast_to(gaussians.log_scales, (len(gaussians), 3))
    cols: dict[str, np.ndarray] = {
        "x": gaussians.means[:, 0],
        "y": gaussians.means[:, 1],
        "z": gaussians.means[:, 2],
    }
    cols.update({f"scale_{i}": scales[:, i] for i in range(3)})
    cols.update({f"rot_{i}": gaussians.quats[:, i] for i in range(4)})
    cols["opacity"] = gaussians.opacity_logits
    cols.update({f"f_dc_{i}": gaussians.sh_dc[:, i] for i in range(3)})
    k = gaussians.sh_rest.shape[1]
    rest = gaussians.sh_rest.transpose(0, 2, 1).reshape(len(gaussians), 3 * k)  # by channel
    cols.update({name: rest[:, i] for i, name in enumerate(f_rest_names(k))})
    if importance:
        cols["importance"] = gaussians.importance
        cols["importance_sum"] = gaussians.importance_sum
        cols["importance_weight"] = gaussians.importance_weight
        cols["alpha_t_sum"] = gaussians.alpha_t_sum
    cols["id"] = gaussians.ids
    return cols


def map_from_columns(cols: Mapping[str, np.ndarray], source: str = "input") -> GaussianMap:
    """Build a map from named columns (extra columns are ignored).

    Missing optional columns get defaults: no higher SH, ids 0..N-1, zero importance. A file that
    holds only the score `importance` (a PLY from another tool) gets importance_sum = score and
    importance_weight = 1, which reproduces the score. When scale_0..2 are bit-identical in every
    row the map is returned isotropic.

    Raises:
        MapError: a required column is missing, or the SH columns are not a whole degree.
    """
    missing = [name for name in REQUIRED if name not in cols]
    if missing:
        raise MapError(f"{source} lacks required field(s): {', '.join(missing)}")
    n_rest = sum(1 for name in cols if name.startswith("f_rest_"))
    if n_rest % 3 or n_rest // 3 not in SH_REST_COUNTS.values():
        raise MapError(f"{source} has {n_rest} f_rest fields; expected 0, 9, 24 or 45")
    k = n_rest // 3
    missing_rest = [name for name in f_rest_names(k) if name not in cols]
    if missing_rest:
        raise MapError(f"{source} lacks field(s): {', '.join(missing_rest)}")

    def stack(names: Iterable[str]) -> np.ndarray:
        return np.stack([np.asarray(cols[name], dtype=np.float32) for name in names], axis=1)

    n = len(cols["x"])
    log_scales = stack(["scale_0", "scale_1", "scale_2"])
    if np.array_equal(log_scales[:, :1], log_scales[:, 1:2]) and np.array_equal(
        log_scales[:, :1], log_scales[:, 2:3]
    ):
        log_scales = log_scales[:, :1]
    rest = stack(f_rest_names(k)).reshape(n, 3, k).transpose(0, 2, 1) if k else None
    sums: dict[str, np.ndarray | None] = {
        name: (np.asarray(cols[name]) if name in cols else None)
        for name in ("importance_sum", "importance_weight", "alpha_t_sum")
    }
    if sums["importance_sum"] is None and "importance" in cols:
        sums["importance_sum"] = np.asarray(cols["importance"])
        sums["importance_weight"] = np.ones(n, np.float32)
    return GaussianMap.new(
        means=stack(["x", "y", "z"]),
        log_scales=log_scales,
        quats=stack([f"rot_{i}" for i in range(4)]),
        opacity_logits=np.asarray(cols["opacity"]),
        sh_dc=stack(["f_dc_0", "f_dc_1", "f_dc_2"]),
        sh_rest=rest,
        ids=np.asarray(cols["id"]) if "id" in cols else None,
        **sums,
    )


def pack_records(cols: Mapping[str, np.ndarray], dtypes: Mapping[str, np.dtype]) -> np.ndarray:
    """Pack columns into one little-endian structured array, fields in the order of `dtypes`."""
    n = len(next(iter(cols.values()))) if cols else 0
    records = np.empty(n, dtype=np.dtype([(name, dtypes[name]) for name in dtypes]))
    for name in dtypes:
        records[name] = cols[name]
    return records


def column_dtypes(cols: Mapping[str, np.ndarray]) -> dict[str, np.dtype]:
    """Little-endian record dtypes for columns: uint32 for `id`, float32 for all else."""
    return {name: np.dtype("<u4" if name == "id" else "<f4") for name in cols}
