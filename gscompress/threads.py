"""How many CPU threads a command may use: one setting for torch and for our own parallel work."""

from __future__ import annotations

import os
import sys

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Read by torch's OpenMP and MKL when it loads, and by `cpu_threads`."""


def use_threads(n: int) -> None:
    """Use `n` CPU threads from here on, without importing torch where it is not loaded yet: the
    variables torch reads when it loads are set, and a torch already loaded is told too."""
    for name in THREAD_VARIABLES:
        os.environ[name] = str(n)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)


def cpu_threads(limit: int | None = None) -> int:
    """Threads for work done outside torch (k-d tree queries, frame writers), at most `limit`:
    the count `use_threads` set (`gsc --threads N`, an experiment worker's share), else the
    machine's cores."""
    value = os.environ.get(THREAD_VARIABLES[0], "")
    n = int(value) if value.isdigit() and int(value) > 0 else (os.cpu_count() or 1)
    return n if limit is None else min(limit, n)
