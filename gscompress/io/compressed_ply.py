"""PlayCanvas's compressed PLY (`.compressed.ply`, written by SuperSplat and splat-transform).

A PLY file with up to three elements:

- `chunk`: one row per 256 Gaussians (in file order), float32 bounds min/max of x y z and of
  the three log scales, optionally min/max of the colour r g b;
- `vertex`: four uint32 per Gaussian: `packed_position` and `packed_scale` (11, 10 and 11 bits,
  each a fraction of its chunk's range, high bits first), `packed_rotation` (2 bits naming the
  largest of rot_0..3, which is positive and left out, then the other three in order as 10-bit
  codes of (q sqrt(1/2) + 1/2)), `packed_color` (r g b as 8-bit fractions of the chunk's colour
  range, or of [0, 1] without one, where colour = 0.5 + SH_C0 f_dc, then the opacity after the
  sigmoid, 8 bits);
- `sh` (optional): f_rest_0.. (channel-major, as 3DGS PLY) as uint8 codes of (v / 8 + 1/2).

Opacity codes 0 and 255 read as a quarter step inside (0, 1), as SPZ's do, so that every logit
is finite. `ply.read_ply` parses the header and calls `decompress` for this layout.
"""

from __future__ import annotations

import numpy as np

from gscompress.errors import MapError, PlyFormatError
from gscompress.gaussians import SH_C0, SH_REST_COUNTS, GaussianMap
from gscompress.io.columns import map_from_columns
from gscompress.io.spz import opacity_logits

CHUNK_SIZE = 256
"""Gaussians per row of the `chunk` element."""

_BOUNDS = ("x", "y", "z", "scale_x", "scale_y", "scale_z")
_COLOUR_BOUNDS = ("r", "g", "b")
_PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")


def decompress(elements: dict[str, np.ndarray], source: str) -> GaussianMap:
    """The validated map of a compressed PLY's elements (name -> structured records).

    Raises:
        PlyFormatError: naming `source`: a missing element or property, a property of another
            type, a chunk or SH count that does not match the vertices, or invalid values.
    """
    vertex = _element(elements, "vertex", _PACKED, "u4", source)
    n = len(vertex)
    chunk_names = [f"{side}_{b}" for side in ("min", "max") for b in _BOUNDS]
    chunk = _element(elements, "chunk", chunk_names, "f4", source)
    if len(chunk) != -(-n // CHUNK_SIZE):
        raise PlyFormatError(
            f"{source}: {len(chunk)} chunk rows for {n} vertices; the compressed layout has one "
            f"per {CHUNK_SIZE}"
        )
    owner = np.arange(n) // CHUNK_SIZE

    def bounds(name: str) -> tuple[np.ndarray, np.ndarray]:
        return chunk[f"min_{name}"][owner], chunk[f"max_{name}"][owner]

    cols: dict[str, np.ndarray] = {}
    for packed, axes in (("packed_position", ("x", "y", "z")), ("packed_scale", _BOUNDS[3:])):
        fractions = _unorm_11_10_11(vertex[packed])
        for i, (axis, t) in enumerate(zip(axes, fractions, strict=True)):
            low, high = bounds(axis)
            cols[axis if packed == "packed_position" else f"scale_{i}"] = _lerp(low, high, t)
    colour = vertex["packed_color"]
    rgb = [_unorm(colour >> shift, 8) for shift in (24, 16, 8)]
    if "min_r" in (chunk.dtype.names or ()):
        colour_names = [f"{side}_{c}" for side in ("min", "max") for c in _COLOUR_BOUNDS]
        _element(elements, "chunk", colour_names, "f4", source)
        rgb = [_lerp(*bounds(c), t) for c, t in zip(_COLOUR_BOUNDS, rgb, strict=True)]
    for i, value in enumerate(rgb):
        cols[f"f_dc_{i}"] = (value - 0.5) / np.float32(SH_C0)
    cols["opacity"] = opacity_logits(_unorm(colour, 8))
    cols.update({f"rot_{i}": q for i, q in enumerate(_rotations(vertex["packed_rotation"]))})
    if "sh" in elements:
        cols.update(_sh(elements["sh"], n, source))
    try:
        return map_from_columns(cols, source).validate()
    except MapError as exc:
        raise PlyFormatError(f"{source}: {exc}") from None


def _element(
    elements: dict[str, np.ndarray],
    name: str,
    props: list[str] | tuple[str, ...],
    kind: str,
    source: str,
) -> np.ndarray:
    """Element `name`, refused unless it has every property of `props` as type `kind`."""
    if name not in elements:
        raise PlyFormatError(f"{source}: compressed PLY without a {name!r} element")
    records = elements[name]
    names = records.dtype.names or ()
    missing = [p for p in props if p not in names]
    if missing:
        raise PlyFormatError(
            f"{source}: compressed PLY {name!r} element lacks {', '.join(missing)}"
        )
    wrong = [p for p in props if records.dtype[p].kind + str(records.dtype[p].itemsize) != kind]
    if wrong:
        raise PlyFormatError(
            f"{source}: compressed PLY {name!r} properties {', '.join(wrong)} must be "
            f"{'uint32' if kind == 'u4' else 'float32'}"
        )
    return records


def _unorm(value: np.ndarray, bits: int) -> np.ndarray:
    """The low `bits` bits of `value` as a fraction in [0, 1]."""
    top = (1 << bits) - 1
    return ((value & top).astype(np.float32) / np.float32(top)).astype(np.float32)


def _unorm_11_10_11(value: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three fractions packed as 11, 10 and 11 bits, high bits first."""
    return _unorm(value >> 21, 11), _unorm(value >> 11, 10), _unorm(value, 11)


def _lerp(low: np.ndarray, high: np.ndarray, t: np.ndarray) -> np.ndarray:
    """low + t (high - low), as the format's writers and readers interpolate (float32 out)."""
    return (low.astype(np.float64) * (1 - t) + high.astype(np.float64) * t).astype(np.float32)


def _rotations(code: np.ndarray) -> list[np.ndarray]:
    """rot_0..3 of packed rotations (the largest component left out, positive)."""
    others = [
        (_unorm(code >> shift, 10) - np.float32(0.5)) * np.float32(np.sqrt(2))
        for shift in (20, 10, 0)
    ]
    largest = (code >> 30).astype(np.intp)
    rest = sum(np.square(v, dtype=np.float32) for v in others)
    m = np.sqrt(np.maximum(0, 1 - rest)).astype(np.float32)
    out = []
    for i in range(4):
        # component i is the largest, or the (i - [largest < i])-th of the others
        before = np.where(largest < i, i - 1, i)
        picked = np.choose(np.clip(before, 0, 2), others)
        out.append(np.where(largest == i, m, picked).astype(np.float32))
    return out


def _sh(records: np.ndarray, n: int, source: str) -> dict[str, np.ndarray]:
    """f_rest_* columns of the `sh` element (uint8 codes)."""
    names = records.dtype.names or ()
    if len(names) // 3 not in SH_REST_COUNTS.values() or len(names) % 3:
        raise PlyFormatError(f"{source}: compressed PLY 'sh' element has {len(names)} properties")
    expected = [f"f_rest_{i}" for i in range(len(names))]
    if sorted(names) != sorted(expected) or any(records.dtype[p] != np.uint8 for p in names):
        raise PlyFormatError(f"{source}: compressed PLY 'sh' element must be uint8 f_rest_0..")
    if len(records) != n:
        raise PlyFormatError(f"{source}: compressed PLY 'sh' has {len(records)} rows, not {n}")
    cols = {}
    for name in expected:
        code = records[name].astype(np.float32)
        fraction = np.where(code == 0, 0, np.where(code == 255, 1, (code + 0.5) / 256))
        cols[name] = ((fraction - 0.5) * 8).astype(np.float32)
    return cols
