"""The quantisation rules of the compact codec, one per transform (linear, through a sigmoid or
asinh, log-linear, smallest-three rotations) and the Morton codes of grid positions; SPZ and
the compact codec share the rotation and Morton layouts (numpy only)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gscompress.errors import InputError
from gscompress.gaussians import GaussianMap

POSITION_STEP_FRACTION = 1 / 128
"""Default position grid step as a fraction of the map's median Gaussian scale (the standard
deviation exp(log_scale)): the position error is at most half a step per axis, 1/256 of a typical
Gaussian's own scale (positions set most of a compact map's error: docs/codecs.md)."""

MAX_POSITION_BITS = 21
"""Largest grid size per axis, in bits (three axes interleave into a 63-bit Morton code)."""

SQRT1_2 = np.float32(np.sqrt(0.5))
"""The largest the three smallest components of a unit quaternion can be."""

FLOAT32_MAX = float(np.finfo(np.float32).max)
"""Largest value a decoded attribute may take (a map holds float32)."""

MAX_ASINH = float(np.arcsinh(np.float64(np.finfo(np.float32).max)))
"""Largest |asinh(value)| an `asinh-linear` column may code (sinh of it is float32's largest)."""

MAX_LOG_SCORE = 88.0
"""Largest log score a `log-linear` column may code (exp of it is a finite float32)."""

SIGMOID_EPS = 1e-7
"""Opacities are coded in [eps, 1 - eps], so that every code has a finite logit."""


def quantise_linear(values: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear codes of `bits` bits for each column of `values` [N, C] between its min and max.

    Returns:
        (codes [N, C] uint8 or uint16, low [C], high [C]); decoding is `dequantise_linear`.
    """
    values = np.asarray(values, dtype=np.float64)
    levels = (1 << bits) - 1
    if len(values):
        low, high = column_ranges(values)
    else:
        low = high = np.zeros(values.shape[1])
    span = np.where(high > low, high - low, 1.0)
    codes = np.rint((values - low) / span * levels)
    return codes.astype(np.uint8 if bits <= 8 else np.uint16), low, high


def column_ranges(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and the largest value of each column of `values` [N, C] (N > 0): ([C],
    [C]), reduced a column at a time (many times faster than along axis 0)."""
    columns = values.reshape(len(values), -1).T
    low = np.array([c.min() for c in columns], dtype=values.dtype)
    high = np.array([c.max() for c in columns], dtype=values.dtype)
    return low, high


def dequantise_linear(
    codes: np.ndarray, low: np.ndarray, high: np.ndarray, bits: int
) -> np.ndarray:
    """Values of linear codes: low + code * (high - low) / (2^bits - 1), as float32."""
    levels = (1 << bits) - 1
    return (low + codes.astype(np.float64) * ((high - low) / levels)).astype(np.float32)


def sigmoid(logits: np.ndarray) -> np.ndarray:
    """Opacity in (0, 1) of opacity logits (float64; no overflow warning at large |logit|)."""
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(logits, dtype=np.float64)))


def logit(p: np.ndarray) -> np.ndarray:
    """Opacity logits of opacities, clamped to [eps, 1 - eps] so that each is finite."""
    p = np.clip(np.asarray(p, dtype=np.float64), SIGMOID_EPS, 1 - SIGMOID_EPS)
    return np.log(p / (1 - p))


def _asinh(values: np.ndarray) -> np.ndarray:
    return np.arcsinh(np.asarray(values, dtype=np.float64))


def _sinh(values: np.ndarray) -> np.ndarray:
    """sinh, within float32's range (an `asinh-linear` column's range is bounded by it)."""
    return np.clip(np.sinh(np.asarray(values, dtype=np.float64)), -FLOAT32_MAX, FLOAT32_MAX)


LINEAR_TRANSFORMS: dict[str, tuple[Callable[[np.ndarray], np.ndarray], ...]] = {
    "linear": (np.asarray, np.asarray),
    "sigmoid-linear": (sigmoid, logit),
    "asinh-linear": (_asinh, _sinh),
}
"""A linear column's transform -> (forward: a value into the space its codes are linear in,
inverse: back). The encoder, the decoder and bench/codec_columns.py take them from here."""


def quantise_log(scores: np.ndarray, bits: int) -> tuple[np.ndarray, float, float]:
    """Codes of nonnegative scores on a log scale: 0 for a zero score, 1..2^bits-1 linear in log
    score between the smallest and largest positive score.

    Returns:
        (codes [N] uint16, low, high: log of the smallest and largest positive score).
    """
    scores = np.asarray(scores, dtype=np.float64)
    positive = scores > 0
    codes = np.zeros(len(scores), np.uint16)
    if not positive.any():
        return codes, 0.0, 0.0
    logs = np.log(scores[positive])
    logs = np.clip(logs, -MAX_LOG_SCORE, MAX_LOG_SCORE)  # (subnormal float32 goes below -88)
    low, high = float(logs.min()), float(logs.max())
    steps = (1 << bits) - 2
    span = high - low if high > low else 1.0
    codes[positive] = 1 + np.rint((logs - low) / span * steps).astype(np.uint16)
    return codes, low, high


def dequantise_log(codes: np.ndarray, low: float, high: float, bits: int) -> np.ndarray:
    """Scores of log codes (see `quantise_log`), as float32: a table of every code's value,
    indexed (codes must be below 2^bits)."""
    steps = (1 << bits) - 2
    table = np.exp(low + (np.arange(1 << bits) - 1.0) * ((high - low) / steps))
    table[0] = 0.0
    return table.astype(np.float32)[codes]


def encode_smallest_three(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N] uint32 smallest-three codes of rotations (w x y z, any nonzero norm), in SPZ's
    layout: the index of the largest |component| (in x y z w order) in the top 2 bits, then
    the other three, each as a sign bit and 9 bits of magnitude in [0, 1/sqrt2], signed so
    that the largest is positive (one layout for SPZ files and compact maps)."""
    norms = np.linalg.norm(np.asarray(quats_wxyz, dtype=np.float64), axis=1, keepdims=True)
    quats_wxyz = np.asarray(quats_wxyz, dtype=np.float64) / np.where(norms > 0, norms, 1.0)
    q = [quats_wxyz[:, i] for i in (1, 2, 3, 0)]  # x y z w
    size = np.abs(quats_wxyz)[:, [1, 2, 3, 0]]
    largest = np.argmax(size, axis=1)  # the first of equal magnitudes, as the reference
    flip = np.choose(largest, q) < 0
    code = largest.astype(np.uint32) << np.uint32(30)
    for i in range(4):
        magnitude = np.minimum(np.floor(size[:, i] * (511 / np.sqrt(0.5)) + 0.5), 511)
        negative = ((q[i] < 0) ^ flip) & (q[i] != 0)
        field = magnitude.astype(np.uint32) | negative.astype(np.uint32) << np.uint32(9)
        slot = i - (largest < i)  # its place among the three stored, first in the high bits
        shift = (10 * (2 - slot)).clip(0).astype(np.uint32)
        code |= np.where(largest != i, field << shift, np.uint32(0)).astype(np.uint32)
    return code


def decode_smallest_three(code: np.ndarray) -> np.ndarray:
    """[N, 4] float32 unit quaternions (w x y z) of `encode_smallest_three` codes."""
    n = len(code)
    largest = (code >> 30).astype(np.intp)
    q = np.zeros((n, 4), np.float32)  # x y z w
    rows = np.arange(n)
    rest = code.astype(np.uint32)
    squares = np.zeros(n, np.float32)
    for i in range(3, -1, -1):
        here = largest != i
        value = (rest & 511).astype(np.float32) * (SQRT1_2 / np.float32(511))
        value = np.where((rest >> 9) & 1, -value, value)
        q[:, i] = np.where(here, value, 0)
        squares += np.where(here, value * value, 0)
        rest = np.where(here, rest >> 10, rest)
    q[rows, largest] = np.sqrt(np.maximum(0, 1 - squares))
    return q[:, [3, 0, 1, 2]]


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Each bit i of 21-bit integers moved to bit 3i (uint64)."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def _compact_bits(v: np.ndarray) -> np.ndarray:
    """The inverse of `_spread_bits`: bits 3i back to bit i."""
    v = v.astype(np.uint64) & np.uint64(0x1249249249249249)
    for shift, mask in (
        (2, 0x10C30C30C30C30C3),
        (4, 0x100F00F00F00F00F),
        (8, 0x1F0000FF0000FF),
        (16, 0x1F00000000FFFF),
        (32, 0x1FFFFF),
    ):
        v = (v | (v >> np.uint64(shift))) & np.uint64(mask)
    return v


def morton_codes(grid: np.ndarray) -> np.ndarray:
    """Morton codes (uint64) of grid coordinates [N, 3] below 2^21: x in bit 0, y 1, z 2."""
    grid = np.asarray(grid)
    return (
        _spread_bits(grid[:, 0])
        | (_spread_bits(grid[:, 1]) << np.uint64(1))
        | (_spread_bits(grid[:, 2]) << np.uint64(2))
    )


def morton_order(codes: np.ndarray, bits: int) -> np.ndarray:
    """`np.argsort(codes, kind="stable")` of codes (uint64) below 2^`bits`, by a radix sort of
    16 bits at a time: numpy sorts 16-bit keys by radix, larger ones by a merge sort several
    times slower."""
    order = np.arange(len(codes))
    for shift in range(0, bits, 16):
        digit = (codes[order] >> np.uint64(shift)).astype(np.uint16)
        order = order[np.argsort(digit, kind="stable")]
    return order


def morton_grid(codes: np.ndarray) -> np.ndarray:
    """Grid coordinates [N, 3] (int64) of Morton codes (the inverse of `morton_codes`)."""
    codes = np.asarray(codes, dtype=np.uint64)
    return np.stack([_compact_bits(codes >> np.uint64(axis)) for axis in range(3)], axis=1).astype(
        np.int64
    )


def position_step(
    gaussians: GaussianMap, step: float | None = None
) -> tuple[np.ndarray, float, int]:
    """The position grid of a map: origin [3] (float64), step and bits per axis.

    The step is `step`, else `POSITION_STEP_FRACTION` of the median scale; it grows where the
    map would span more than 2^MAX_POSITION_BITS steps along an axis.

    Raises:
        InputError: a given step that is not a positive finite number.
    """
    if step is not None and not (np.isfinite(step) and step > 0):
        raise InputError(f"position step must be a positive number of metres, got {step}")
    means = gaussians.means.astype(np.float64)
    if not len(means):
        return np.zeros(3), float(step or 1.0), 1
    origin, top = column_ranges(means)
    extent = float((top - origin).max())
    if step is None:
        median_scale = float(np.median(np.exp(gaussians.log_scales.astype(np.float64))))
        step = POSITION_STEP_FRACTION * median_scale if median_scale > 0 else 1e-3
    step = max(step, extent / ((1 << MAX_POSITION_BITS) - 1) * (1 + 1e-9), np.finfo(float).tiny)
    bits = max(1, int(np.ceil(np.log2(extent / step + 1.5))))
    return origin, float(step), min(bits, MAX_POSITION_BITS)


def grid_codes(
    gaussians: GaussianMap, step: float | None = None
) -> tuple[np.ndarray, float, int, np.ndarray]:
    """The position grid of a map (`position_step`: origin, step, bits per axis) and each
    Gaussian's Morton code on it; a compact message stores the Gaussians in that code's order.

    Raises:
        InputError: a bad `step`.
    """
    origin, step, bits = position_step(gaussians, step)
    grid = np.rint((gaussians.means.astype(np.float64) - origin) / step).astype(np.int64)
    return origin, step, bits, morton_codes(np.clip(grid, 0, (1 << bits) - 1))
