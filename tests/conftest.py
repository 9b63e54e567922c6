"""Fixtures shared by several test modules."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator

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


@pytest.fixture
def terminated() -> Callable[..., tuple[int, str]]:
    """Run a command, send it SIGTERM once `ready()` holds; its exit code and stderr."""
    return _terminated


def _terminated(cmd: list[str], ready: Callable[[], bool], timeout: float = 300) -> tuple[int, str]:
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + timeout
        while not ready():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=timeout)
    finally:
        proc.kill()
    return proc.returncode, stderr
