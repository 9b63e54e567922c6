"""What the fuzz targets build their edits from: where choices come from (`Chooser`), the edge
values written into fields, and raw byte edits."""

from __future__ import annotations

import random
from collections.abc import Sequence
from typing import Any, Protocol

INTERESTING = (
    0,
    1,
    2,
    7,
    8,
    9,
    21,
    22,
    255,
    256,
    2**15,
    2**16 - 1,
    2**16,
    2**31 - 1,
    2**31,
    2**32 - 1,
    2**32,
    2**32 + 1,
    2**36,
    2**40,
    2**62,
    2**63 - 1,
    2**63,
    2**64 - 1,
)
"""Values written into length, count, offset and size fields."""

SPECIAL_FLOATS = (
    0.0,
    -0.0,
    1.0,
    -1.0,
    1e-45,
    1e30,
    -1e30,
    3.4e38,
    -3.4e38,
    float("inf"),
    float("-inf"),
    float("nan"),
    88.0,
    -88.0,
    710.0,
    65504.0,
    65520.0,
)
"""Values written into float fields (PointCloud and PLY records)."""


class Chooser(Protocol):
    """Where a mutator's choices come from."""

    def integer(self, low: int, high: int) -> int:
        """An integer in [low, high]."""
        ...

    def pick(self, options: Sequence[Any]) -> Any:
        """One of `options`."""
        ...


class RandomChooser:
    """Choices from a seeded `random.Random`."""

    def __init__(self, seed: int):
        self.rng = random.Random(seed)

    def integer(self, low: int, high: int) -> int:
        return self.rng.randint(low, high)

    def pick(self, options: Sequence[Any]) -> Any:
        return options[self.rng.randrange(len(options))]


def edge_value(c: Chooser, width: int) -> int:
    """An interesting or random unsigned value that fits `width` bytes."""
    top = 2 ** (8 * width) - 1
    if c.integer(0, 3) == 0:
        return c.integer(0, top)
    return min(c.pick(INTERESTING), top)


def overwrite(data: bytes, c: Chooser, start: int = 0, end: int | None = None) -> bytes:
    """`data` with an integer field (1, 2, 4 or 8 bytes) in [start, end) set to a chosen value."""
    end = len(data) if end is None else min(end, len(data))
    width = c.pick((1, 2, 4, 8))
    if end - start < width:
        return data
    at = c.integer(start, end - width)
    value = edge_value(c, width).to_bytes(width, "little")
    return data[:at] + value + data[at + width :]


def byte_mutation(data: bytes, c: Chooser) -> bytes:
    """One raw edit: a field overwritten, bytes flipped, cut, inserted, deleted or repeated."""
    kind = c.integer(0, 5)
    at = c.integer(0, max(len(data) - 1, 0))
    if kind == 0:
        return overwrite(data, c)
    if kind == 1 and data:
        return data[:at] + bytes([data[at] ^ (1 << c.integer(0, 7))]) + data[at + 1 :]
    if kind == 2:
        return data[:at]
    if kind == 3:
        return data[:at] + bytes(c.pick((1, 8, 64, 4096))) + data[at:]
    if kind == 4:
        return data[:at] + data[at + c.integer(1, 64) :]
    return data[:at] + data[at : at + c.integer(1, 256)] * c.integer(2, 4) + data[at:]
