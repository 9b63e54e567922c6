"""Seeded random generators, with the one check of a seed that every caller shares."""

from __future__ import annotations

import numpy as np

from gscompress.errors import InputError


def check_seed(seed: int) -> int:
    """`seed` if it is a valid seed (an integer >= 0, what numpy accepts), else InputError."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"seed must be an integer >= 0, got {seed!r}")
    return int(seed)


def seeded_rng(seed: int) -> np.random.Generator:
    """numpy's generator for `seed` (checked: a negative seed is an InputError, not numpy's)."""
    return np.random.default_rng(check_seed(seed))
