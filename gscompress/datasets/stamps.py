"""Pairing two streams of timestamps, as TUM's `associate.py` does, in N log N.

`associate(a, b, max_dt)` is the one pairing rule of every reader: the TUM folder's rgb.txt and
depth.txt, and a recording's colour and depth messages. The rule (associate.py's): every pair
whose times differ by less than `max_dt` is a candidate; candidates are taken greedily by the
smallest difference, ties by the smaller index into `a`, then into `b`; each stamp is used at
most once; the pairs come out ordered by `a`'s time.

Taken literally the rule lists every candidate pair first, which is N x M pairs for lists that
share one timestamp (3000 rows each: 9 million pairs, some 1.5 GB). Here the same pairs come
from a merge of the two sorted lists: stamps of one list with equal times form a group, used in
index order, and the smallest remaining candidate is always between two groups that are
neighbours in time order, so a heap over neighbouring groups finds each pair in log time.
"""

from __future__ import annotations

import heapq

import numpy as np


def associate(a: np.ndarray, b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """One-to-one association of timestamps `a` [N] and `b` [M] (TUM associate.py rule).

    Time O((N + M) log(N + M)), memory O(N + M). The differences are computed as
    `abs(a[i] - b[j])` in float64, as the literal rule does; the pairs are the literal rule's
    whenever two unequal stamps of one list are never equally far from a stamp of the other
    after rounding (true of any stamps of the same sign, such as seconds since 1970 or since
    the start of a recording, written to a microsecond or a nanosecond).

    Returns:
        (i, j) index pairs with |a[i] - b[j]| < max_dt, greedy by smallest difference (ties by
        i, then j), each index used once, sorted by a[i] (ties by i).
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    groups = _groups(a, b)  # [(time, side, [indices increasing])] in time order
    n = len(groups)
    left = list(range(-1, n - 1))
    right = [*range(1, n), -1]
    taken = [0] * n  # how many of each group's indices are used (they go in index order)
    heap: list[tuple[float, int, int, int, int]] = []

    def push(g: int) -> None:
        """The candidate between group g and its right neighbour, if they are of both lists."""
        h = right[g]
        if h < 0 or groups[g][1] == groups[h][1]:
            return
        dt = abs(groups[g][0] - groups[h][0])
        if dt < max_dt:
            ga, gb = (g, h) if groups[g][1] == 0 else (h, g)
            i, j = groups[ga][2][taken[ga]], groups[gb][2][taken[gb]]
            heapq.heappush(heap, (dt, i, j, ga, gb))

    for g in range(n - 1):
        push(g)
    pairs: list[tuple[int, int]] = []
    while heap:
        _, i, j, ga, gb = heapq.heappop(heap)
        if not (_current(groups, taken, ga) == i and _current(groups, taken, gb) == j):
            continue  # stale: one side was used since (its group moved on or emptied)
        if right[ga] != gb and right[gb] != ga:
            continue  # (a group between them emptied and was unlinked; a fresh entry exists)
        pairs.append((i, j))
        for g in (ga, gb):
            taken[g] += 1
            if taken[g] == len(groups[g][2]):  # emptied: its neighbours meet
                lo, hi = left[g], right[g]
                if lo >= 0:
                    right[lo] = hi
                if hi >= 0:
                    left[hi] = lo
                left[g] = right[g] = -1
                if lo >= 0:
                    push(lo)
        for g in (ga, gb):  # a group that remains offers its next index to both neighbours
            if taken[g] < len(groups[g][2]):
                push(g)
                if left[g] >= 0:
                    push(left[g])
    pairs.sort(key=lambda p: (a[p[0]], p[0]))
    return pairs


def _groups(a: np.ndarray, b: np.ndarray) -> list[tuple[float, int, list[int]]]:
    """Stamps of `a` (side 0) and `b` (side 1) merged in time order, equal times of one side
    gathered into one group that lists its indices in increasing order."""
    times = np.concatenate([a, b])
    sides = np.concatenate([np.zeros(len(a), np.int64), np.ones(len(b), np.int64)])
    index = np.concatenate([np.arange(len(a)), np.arange(len(b))])
    order = np.lexsort((index, sides, times))
    groups: list[tuple[float, int, list[int]]] = []
    for k in order.tolist():
        t, side, i = float(times[k]), int(sides[k]), int(index[k])
        if groups and groups[-1][0] == t and groups[-1][1] == side:
            groups[-1][2].append(i)
        else:
            groups.append((t, side, [i]))
    return groups


def _current(groups: list[tuple[float, int, list[int]]], taken: list[int], g: int) -> int:
    """The next unused index of group g, or -1 when it has none left."""
    members = groups[g][2]
    return members[taken[g]] if taken[g] < len(members) else -1
