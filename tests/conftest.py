"""Fixtures shared by several test modules."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest


@pytest.fixture
def threads_restored() -> Iterator[None]:
    """`gsc --threads N` sets OMP/MKL_NUM_THREADS and torch's thread count for the whole
    process; put them back after the test, so that later tests run as before."""
    import torch

    names = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")
    saved, before = {name: os.environ.get(name) for name in names}, torch.get_num_threads()
    yield
    torch.set_num_threads(before)
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
