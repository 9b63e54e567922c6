"""Named per-Gaussian columns: the one mapping between GaussianMap and packed records.

Both file formats (the MCAP `/gaussians` PointCloud and 3DGS PLY) store a map as records of
named scalar fields, with the 3DGS PLY names: x y z, scale_0..2 (log), rot_0..3 (w x y z),
opacity (logit), f_dc_0..2, f_rest_* (channel-major, as the INRIA PLY writer lays them out),
plus our own importance, importance_sum, importance_weight, alpha_t_sum and id. This module turns
a map into such columns and back, and packs / unpacks columns as little-endian records.

Precision: columns are float32, or, at half precision (the `fp16` codec), every column whose
values are bounded by design (log scales, rotations, opacity logit, SH) is stored as IEEE 754
binary16 bit patterns in a uint16 column named `<name>_f16`. Positions stay float32 (viewers
place the cloud by them) and so do the importance score and sums, which grow with image size and
frame count and can exceed the float16 range (65504). Decoding turns `_f16` columns back into
float32 ones of the plain name.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping

import numpy as np

from gscompress.errors import MapError
from gscompress.gaussians import SH_REST_COUNTS, GaussianMap

GEOMETRY = ("x", "y", "z", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
"""Required columns for position, shape and orientation."""

APPEARANCE = ("opacity", "f_dc_0", "f_dc_1", "f_dc_2")
"""Required columns for opacity and base colour."""

REQUIRED = GEOMETRY + APPEARANCE

MAX_ABS_OPACITY_LOGIT = 80.0
"""Opacity logits read from a file are clamped to +-this: float32 rounds the sigmoid of +17 to 1,
that of -80 is 2e-35, and exp() of 89 already overflows float32 (of 710, float64)."""

logger = logging.getLogger(__name__)

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


def map_from_columns(
    cols: Mapping[str, np.ndarray], source: str = "input", infinite_opacity: bool = False
) -> GaussianMap:
    """Build a map from named columns (extra columns are ignored).

    Missing optional columns get defaults: no higher SH, ids 0..N-1, zero importance. A file that
    holds only the score `importance` (a PLY from another tool) gets importance_sum = score and
    importance_weight = 1, which reproduces the score. When scale_0..2 are bit-identical in every
    row the map is returned isotropic.

    Opacity logits beyond +-`MAX_ABS_OPACITY_LOGIT` are clamped to it, with one warning; with
    `infinite_opacity` also +-inf (opacity exactly 1 or 0, as some converters write it). NaN
    and, without `infinite_opacity`, infinities are left for `GaussianMap.validate` to refuse.

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
        with np.errstate(over="ignore"):  # a float64 beyond float32 becomes inf: validate says so
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
        opacity_logits=_bounded_logits(np.asarray(cols["opacity"]), source, infinite_opacity),
        sh_dc=stack(["f_dc_0", "f_dc_1", "f_dc_2"]),
        sh_rest=rest,
        ids=_ids(cols["id"], source) if "id" in cols else None,
        **sums,
    )


def _bounded_logits(logits: np.ndarray, source: str, infinite: bool) -> np.ndarray:
    """Opacity logits clamped to +-`MAX_ABS_OPACITY_LOGIT` (infinities only when `infinite`)."""
    as_float = logits.astype(np.float64)
    with np.errstate(invalid="ignore"):  # (NaN compares false: left for validate)
        beyond = np.abs(as_float) > MAX_ABS_OPACITY_LOGIT
    if not infinite:
        beyond &= np.isfinite(as_float)
    count = int(np.count_nonzero(beyond))
    if not count:
        return logits
    infinities = int(np.count_nonzero(np.isinf(as_float)))
    parts = [f"{infinities} infinite"] if infinities else []
    if count > infinities:
        parts.append(f"{count - infinities} beyond +-{MAX_ABS_OPACITY_LOGIT:g}")
    logger.warning(
        "%s: %s opacity logit(s) read as +-%g (opacity 1 or 0)",
        source,
        " and ".join(parts),
        MAX_ABS_OPACITY_LOGIT,
    )
    clamped = np.where(beyond, np.sign(as_float) * MAX_ABS_OPACITY_LOGIT, as_float)
    return clamped.astype(np.float32)


def _ids(values: np.ndarray, source: str) -> np.ndarray:
    """An `id` column as uint32, refusing values that are not whole numbers in [0, 2^32) (a
    PLY may declare the property as any numeric type)."""
    values = np.asarray(values)
    if values.dtype.kind == "u" and values.dtype.itemsize <= 4:
        return values.astype(np.uint32)
    as_float = values.astype(np.float64)
    if not np.all((as_float >= 0) & (as_float < 2**32) & (as_float == np.floor(as_float))):
        raise MapError(f"{source}: id has values that are not whole numbers in [0, 2^32)")
    return as_float.astype(np.uint32)


def pack_records(cols: Mapping[str, np.ndarray], dtypes: Mapping[str, np.dtype]) -> np.ndarray:
    """Pack columns into one little-endian structured array, fields in the order of `dtypes`."""
    n = len(next(iter(cols.values()))) if cols else 0
    records = np.empty(n, dtype=np.dtype([(name, dtypes[name]) for name in dtypes]))
    for name in dtypes:
        records[name] = cols[name]
    return records


def column_dtypes(cols: Mapping[str, np.ndarray]) -> dict[str, np.dtype]:
    """Little-endian record dtypes: uint32 for `id`, uint16 for `*_f16`, float32 for all else."""
    return {
        name: np.dtype("<u4" if name == "id" else "<u2" if name.endswith(HALF_SUFFIX) else "<f4")
        for name in cols
    }


HALF_SUFFIX = "_f16"
"""Name suffix of a uint16 column that holds the float16 bit patterns of a float column."""

FLOAT32_ALWAYS = ("x", "y", "z", "importance", "importance_sum", "importance_weight", "alpha_t_sum")
"""Columns kept float32 at every precision (positions; unbounded scores and sums)."""

HALF_MAX = float(np.finfo(np.float16).max)
"""Largest finite float16 (65504)."""


def encode_columns(cols: Mapping[str, np.ndarray], half: bool) -> dict[str, np.ndarray]:
    """Columns as stored: unchanged, or with `half` the bounded ones as float16 bit patterns.

    Values round to the nearest float16; a finite value that would round to infinity is refused
    (non-finite values pass through, for the reader's checks to refuse).

    Raises:
        MapError: a value outside the float16 range.
    """
    if not half:
        return dict(cols)
    out: dict[str, np.ndarray] = {}
    for name, values in cols.items():
        if name == "id" or name in FLOAT32_ALWAYS:
            out[name] = values
            continue
        values = np.asarray(values, dtype=np.float32)
        with np.errstate(over="ignore"):  # overflow is reported below, by column
            halves = values.astype(np.float16)
        overflow = np.isinf(halves) & np.isfinite(values)
        if overflow.any():
            worst = float(values[overflow][np.argmax(np.abs(values[overflow]))])
            raise MapError(
                f"{name} holds {int(overflow.sum())} value(s) beyond the float16 range "
                f"(|v| > {HALF_MAX:g}, e.g. {worst:g}); use precision fp32"
            )
        out[name + HALF_SUFFIX] = halves.view("<u2")
    return out


def decode_columns(cols: Mapping[str, np.ndarray], source: str = "input") -> dict[str, np.ndarray]:
    """Stored columns back to plain ones: each uint16 `<name>_f16` becomes float32 `<name>`.

    Raises:
        MapError: a `_f16` column that is not uint16, is `id_f16`, or repeats a plain column.
    """
    out: dict[str, np.ndarray] = {}
    for name, values in cols.items():
        if not name.endswith(HALF_SUFFIX):
            out[name] = values
            continue
        plain = name[: -len(HALF_SUFFIX)]
        values = np.asarray(values)
        if values.dtype.kind != "u" or values.dtype.itemsize != 2 or plain == "id":
            raise MapError(f"{source}: field {name!r} must be a uint16 float16 field")
        if plain in cols:
            raise MapError(f"{source}: field {plain!r} appears twice ({plain!r} and {name!r})")
        out[plain] = values.astype("<u2").view("<f2").astype(np.float32)
    return out


def has_half_columns(names: Iterable[str]) -> bool:
    """Whether stored columns are at half precision: some column is a `_f16` one."""
    return any(name.endswith(HALF_SUFFIX) for name in names)
