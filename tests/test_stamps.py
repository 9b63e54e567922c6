"""Timestamp association (`gscompress.datasets.stamps.associate`): the TUM associate.py rule in
N log N, checked against the literal rule and for bounded memory on one shared stamp."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gscompress.datasets.stamps import associate


def literal_associate(a: np.ndarray, b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """The rule as it is written (and as the TUM reader had it): every candidate pair listed,
    sorted by (difference, i, j), taken greedily. N x M in time and memory."""
    order = np.argsort(b, kind="stable")
    b_sorted = b[order]
    lo = np.searchsorted(b_sorted, a - max_dt, side="left")
    hi = np.searchsorted(b_sorted, a + max_dt, side="right")
    candidates: list[tuple[float, int, int]] = []
    for i in range(len(a)):
        for k in range(lo[i], hi[i]):
            dt = abs(float(a[i]) - float(b_sorted[k]))
            if dt < max_dt:
                candidates.append((dt, i, int(order[k])))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs: list[tuple[int, int]] = []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    pairs.sort(key=lambda p: (a[p[0]], p[0]))
    return pairs


def _stamps(draw: st.DrawFn, base: float, period: float, n: int) -> np.ndarray:
    """n stamps near a regular clock: jittered, some repeated, some dropped, written to a
    microsecond as TUM's lists are (or to a nanosecond, as a recording's are)."""
    jitter = draw(st.floats(0.0, 1.5 * period))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    t = base + np.arange(n) * period + rng.uniform(-jitter, jitter, n)
    repeats = rng.random(n) < draw(st.floats(0.0, 0.5))  # a stamp shared with the one before
    t[1:][repeats[1:]] = t[:-1][repeats[1:]]
    t = t[rng.random(n) >= draw(st.floats(0.0, 0.3))]
    rng.shuffle(t)  # lists need not be in time order
    decimals = draw(st.sampled_from([3, 6, 9]))
    return np.round(t, decimals)


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_associate_gives_the_literal_rules_pairs(data: st.DataObject) -> None:
    base = data.draw(st.sampled_from([0.0, 12.5, 1305031102.175304, 1.7e9]))
    period_a = data.draw(st.sampled_from([1 / 30, 0.02, 0.01, 0.001]))
    period_b = data.draw(st.sampled_from([1 / 30, 0.02, 0.01, 1 / 15]))
    a = _stamps(data.draw, base, period_a, data.draw(st.integers(0, 60)))
    b = _stamps(data.draw, base, period_b, data.draw(st.integers(0, 60)))
    max_dt = data.draw(st.sampled_from([0.02, 0.005, 0.05, 1e-3]))
    assert associate(a, b, max_dt) == literal_associate(a, b, max_dt)


def test_associate_on_equal_distances_and_shared_stamps() -> None:
    # equally far on both sides: the smaller index of b wins, then of a
    a, b = np.array([10.0, 10.0, 10.5]), np.array([10.25, 9.75, 10.0, 10.0])
    for max_dt in (0.3, 0.6, 0.1, 1e-9):
        assert associate(a, b, max_dt) == literal_associate(a, b, max_dt)
    same = np.full(50, 3.0)
    assert associate(same, same[:20], 0.02) == [(i, i) for i in range(20)]
    assert associate(np.array([]), same, 0.02) == []
    assert associate(
        np.array([0.0, 0.033, 0.066, 0.5]), np.array([0.001, 0.03, 0.031, 0.07, 0.9]), 0.02
    ) == [(0, 0), (1, 2), (2, 3)]


def test_3000_rows_sharing_one_stamp_pair_in_bounded_memory() -> None:
    """The hostile lists of rgb.txt and depth.txt (3000 rows, one timestamp): paired within
    a 64 MB rise of the address space (the literal rule takes some 1.5 GB)."""
    script = textwrap.dedent(
        """
        import resource
        import numpy as np
        from gscompress.datasets.stamps import associate

        stamps = np.full(3000, 1305031102.175304)
        with open("/proc/self/statm") as f:
            mapped = int(f.read().split()[0]) * resource.getpagesize()
        limit = mapped + 64 * 2**20
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        pairs = associate(stamps, stamps.copy(), 0.02)
        assert pairs == [(i, i) for i in range(3000)], pairs[:3]
        print("ok")
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=120,
        env={"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", **_env()},
    )
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]


def _env() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if k in ("PATH", "PYTHONPATH", "HOME")}
