"""Share budgets: a fraction of a map's Gaussians, or a number of bytes on the wire.

A budget is written either as a bare fraction in (0, 1] (`0.2`, or a percentage `20%`) or as a
byte count with a unit: `B`, `kB`, `MB`, `GB` (powers of 1000) or `KiB`, `MiB`, `GiB` (powers of
1024), e.g. `2MB`, `500kB`, `1.5MiB`, `300000B`; the prefix may be written in either case, but the
final `B` must be a capital: a lowercase `b` means bits in link speeds (`2Mb` is 250 kB), so it
is refused rather than read as bytes 8x too many. A fractional byte count is
rounded down (a budget is never exceeded). A bare number above 1 is refused: it is most likely a
byte count that lacks its unit. A percentage of bytes, `5%bytes`, is that share of the map's
own `/gaussians` message at fp32 (the same fraction of every map, as a rate-distortion sweep
wants); it becomes a byte count once the map is known (`Budget.resolve`).

A byte budget counts what is sent: the whole share file as written. The caller supplies that size
as a function of the Gaussian count (`largest_count_within`), so this module stays free of any
file format.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from gscompress.errors import BudgetError, InputError
from gscompress.selection import is_fraction, keep_count, percent_hint

_UNITS = {
    "B": 1,
    "kB": 1000,
    "MB": 1000**2,
    "GB": 1000**3,
    "KiB": 1024,
    "MiB": 1024**2,
    "GiB": 1024**3,
}
BYTE_UNITS: dict[str, int] = {name.lower(): size for name, size in _UNITS.items()}
"""Byte units (lower case: the prefix is read in either case) and their sizes in bytes."""
_SPELLING = {name.lower(): name for name in _UNITS}

_BUDGET = re.compile(
    r"\s*(\d+(?:\.\d*)?|\.\d+)(?:[eE]([+-]?\d+))?\s*(%\s*bytes|%|[a-zA-Z]+)?\s*", re.IGNORECASE
)


@dataclass(frozen=True)
class Budget:
    """A share budget: a fraction of the Gaussians, a number of bytes, or a fraction of the
    map's bytes at fp32 (which `resolve` turns into a number of bytes once the map is known).

    Attributes:
        ratio: fraction of the map's Gaussians to send, in (0, 1], or None.
        budget_bytes: the most bytes the sent file may take (>= 1), or None.
        fp32_fraction: the budget as a fraction of the map's `/gaussians` message at fp32
            (`5%bytes`), or None; with `budget_bytes` unset until resolved.
        text: how the budget was written (for messages and records).
    """

    ratio: float | None = None
    budget_bytes: int | None = None
    fp32_fraction: float | None = None
    text: str = ""

    def __post_init__(self) -> None:
        if self.ratio is not None and (self.budget_bytes, self.fp32_fraction) != (None, None):
            raise InputError("a budget is a fraction of the Gaussians or a number of bytes")
        if self.ratio is None and self.budget_bytes is None and self.fp32_fraction is None:
            raise InputError("a budget is either a fraction or a number of bytes")
        if self.fp32_fraction is not None and not (
            math.isfinite(self.fp32_fraction) and self.fp32_fraction > 0
        ):
            raise InputError(f"a fraction of the map's bytes must be above 0, got {self.text}")
        if self.ratio is not None and not is_fraction(self.ratio):
            raise InputError(f"budget fraction must be in (0, 1], got {self.ratio:g}")
        if self.budget_bytes is not None and self.budget_bytes < 1:
            raise InputError(f"budget must be at least 1 byte, got {self.budget_bytes}")

    def __str__(self) -> str:
        if self.text:
            return self.text
        return f"{self.ratio:g}" if self.ratio is not None else f"{self.budget_bytes}B"

    def count(self, n: int, message_bytes: Callable[[int], int]) -> int:
        """How many of `n` Gaussians this budget sends.

        Args:
            n: Gaussians available.
            message_bytes: exact size in bytes of the output holding K Gaussians (used by byte
                budgets only; see `largest_count_within`).

        Raises:
            BudgetError: the budget holds no Gaussian.
        """
        if self.ratio is not None:
            return keep_count(n, self.ratio, "budget")
        if self.budget_bytes is None:
            raise InputError(f"budget {self}: resolve it against the map's fp32 bytes first")
        return largest_count_within(self.budget_bytes, n, message_bytes)

    def resolve(self, fp32_bytes: int) -> Budget:
        """This budget with a fraction of the map's bytes turned into bytes, given the map's
        `/gaussians` message at fp32 (`fp32_bytes`); any other budget as it is.

        Raises:
            BudgetError: the fraction comes to less than one byte.
        """
        if self.fp32_fraction is None or self.budget_bytes is not None:
            return self
        budget_bytes = math.floor(self.fp32_fraction * fp32_bytes)
        if budget_bytes < 1:
            raise BudgetError(f"budget {self} of a {fp32_bytes}-byte map is under one byte")
        return Budget(budget_bytes=budget_bytes, fp32_fraction=self.fp32_fraction, text=str(self))

    def record(self) -> dict[str, Any]:
        """The budget as recorded in provenance and results: `budget` [and `budget_bytes`, and
        `budget_fp32_fraction` for a fraction of the map's bytes]."""
        if self.ratio is not None:
            return {"budget": self.ratio}
        out: dict[str, Any] = {"budget": str(self), "budget_bytes": self.budget_bytes}
        if self.fp32_fraction is not None:
            out["budget_fp32_fraction"] = self.fp32_fraction
        return out

    @classmethod
    def parse(cls, value: str | float | Budget) -> Budget:
        """Read a budget from its written form (see the module docstring) or a number.

        Raises:
            InputError: not a number, an unknown unit or one ending in a lowercase b (bits), a
                fraction outside (0, 1], a bare number above 1, or a byte count below one byte.
        """
        if isinstance(value, Budget):
            return value
        if isinstance(value, int | float) and not isinstance(value, bool):
            return cls._from_number(float(value), f"{value:g}")
        text = str(value).strip()
        m = _BUDGET.fullmatch(text)
        if m is None:
            raise InputError(
                f"budget {text!r} is neither a fraction such as 0.2 or 20% nor a size such as "
                "2MB, 500kB or 1.5MiB"
            )
        number = float(m.group(1) + (f"e{m.group(2)}" if m.group(2) else ""))
        unit = m.group(3)
        if unit is None:
            return cls._from_number(number, text)
        if unit == "%":
            return cls._from_number(number / 100, text, percent=True)
        if unit.startswith("%"):  # %bytes: of the map's bytes at fp32
            return cls(fp32_fraction=number / 100, text=text)
        if unit.endswith("b"):
            raise InputError(
                f"budget {text!r}: a lowercase b means bits; budgets are bytes, e.g. "
                f"{m.group(1)}{_SPELLING.get(unit.lower(), unit[:-1] + 'B')}"
            )
        scale = BYTE_UNITS.get(unit.lower())
        if scale is None:
            raise InputError(f"budget {text!r} has unknown unit {unit!r}; use {', '.join(_UNITS)}")
        if not (math.isfinite(number * scale) and number * scale >= 1):
            raise InputError(f"budget {text!r} is not a finite byte count of at least 1 B")
        return cls(budget_bytes=math.floor(number * scale), text=text)

    @classmethod
    def _from_number(cls, number: float, text: str, percent: bool = False) -> Budget:
        if math.isfinite(number) and number > 1.0 and not percent:
            hint = percent_hint(number)
            raise InputError(
                f"budget {text} is above 1: a bare number is a fraction in (0, 1]"
                + (f" (did you mean {hint}?)" if hint else "")
                + f"; for bytes add a unit, e.g. {text}B, {text}kB or {text}MB"
            )
        if not is_fraction(number):
            raise InputError(f"budget {text} is not a fraction in (0, 1]")
        return cls(ratio=number, text=text)


def largest_count_within(budget_bytes: int, n: int, size_of: Callable[[int], int]) -> int:
    """The largest K <= n whose output takes at most `budget_bytes` bytes.

    Args:
        budget_bytes: the most bytes the output may take.
        n: Gaussians available.
        size_of: size in bytes of the output holding K Gaussians, nondecreasing in K (a share
            file: measured by writing it, so each call may be costly).

    Returns:
        K, with size_of(K) <= budget_bytes < size_of(K + 1) (K < n). The search alternates a
        guess interpolated between the sizes of the bracket with a bisection, so it takes
        O(log n) calls and usually a handful.

    Raises:
        BudgetError: not even one Gaussian (or, for an empty map, the empty output) fits.
    """
    first = size_of(min(n, 1))
    if first > budget_bytes:
        what = "one Gaussian" if n else "an empty map"
        raise BudgetError(
            f"a budget of {budget_bytes} B cannot hold {what}: that takes {first} B "
            f"({size_of(0)} B without any Gaussian); raise the budget"
        )
    lo, lo_size = min(n, 1), first  # fits
    if n <= 1 or size_of(n) <= budget_bytes:
        return n
    hi, hi_size = n, size_of(n)  # does not fit
    interpolate = True
    while hi - lo > 1:
        if interpolate:
            guess = lo + int((hi - lo) * (budget_bytes - lo_size) / max(hi_size - lo_size, 1))
        else:
            guess = (lo + hi) // 2
        mid = min(max(guess, lo + 1), hi - 1)
        interpolate = not interpolate
        size = size_of(mid)
        if size <= budget_bytes:
            lo, lo_size = mid, size
        else:
            hi, hi_size = mid, size
    return lo
