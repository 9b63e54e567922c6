"""Budgeted selection: exact counts, top of the score, deterministic ties, never over budget."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscompress.errors import BudgetError, InputError
from gscompress.gaussians import random_map
from gscompress.selection import keep_count, select_top, strategy_scores, top_k


@pytest.mark.parametrize(
    "n, ratio, expected",
    [
        (10, 0.3, 3),
        (10, 0.35, 4),
        (10, 0.25, 3),
        (10, 0.24, 2),
        (7, 1.0, 7),
        (1000, 0.2, 200),
        (3, 0.5, 2),
        (1, 0.5, 1),
        (0, 0.5, 0),
    ],
)
def test_keep_count_rounds_half_up(n, ratio, expected):
    assert keep_count(n, ratio) == expected


@pytest.mark.parametrize("ratio", [0.0, -0.1, 1.01, float("nan"), float("inf")])
def test_ratio_outside_unit_interval_is_refused(ratio):
    with pytest.raises(InputError, match=r"in \(0, 1\]"):
        keep_count(10, ratio)


def test_ratio_rounding_to_nothing_is_an_error():
    with pytest.raises(BudgetError, match="rounds to none"):
        keep_count(10, 0.01)


@settings(max_examples=200, deadline=None)
@given(
    scores=st.lists(st.integers(0, 5), min_size=1, max_size=60),  # small range: many ties
    ratio=st.floats(0.01, 1.0),
    seed=st.integers(0, 1000),
)
def test_top_k_properties(scores, ratio, seed):
    scores = np.asarray(scores, dtype=np.float64)
    n = len(scores)
    ids = np.random.default_rng(seed).permutation(n).astype(np.uint32)
    k = min(n, int(np.floor(ratio * n + 0.5)))
    index = top_k(scores, ids, k)
    assert len(index) == k  # exact count, never over
    assert len(np.unique(index)) == k and np.all(np.diff(index) > 0)
    rest = np.setdiff1d(np.arange(n), index)
    if k and rest.size:
        # everything kept scores at least as high as everything dropped
        assert scores[index].min() >= scores[rest].max()
        # among ties at the threshold, lower ids are kept
        t = scores[index].min()
        kept_tied, dropped_tied = ids[index][scores[index] == t], ids[rest][scores[rest] == t]
        if dropped_tied.size:
            assert kept_tied.max() < dropped_tied.min()
    # the same set comes back whatever the storage order
    perm = np.random.default_rng(seed + 1).permutation(n)
    again = perm[top_k(scores[perm], ids[perm], k)]
    assert set(again.tolist()) == set(index.tolist())


def test_select_top_keeps_highest_pwas():
    g = random_map(1000, seed=3)
    kept, index = select_top(g, 0.3, "pwas")
    assert len(kept) == 300
    assert kept.importance.min() >= np.delete(g.importance, index).max()
    assert kept.equals(g.select(index))


def test_strategies_rank_by_their_score():
    g = random_map(500, seed=4)
    for strategy, score in [("opacity", g.opacity_logits), ("alpha-t", g.alpha_t_sum)]:
        _kept, index = select_top(g, 0.1, strategy)
        assert score[index].min() >= np.delete(score, index).max()
    a, _ = select_top(g, 0.1, "random", seed=1)
    b, _ = select_top(g, 0.1, "random", seed=1)
    c, _ = select_top(g, 0.1, "random", seed=2)
    assert a.equals(b) and not np.array_equal(a.ids, c.ids)


def test_pwas_without_scores_says_how_to_get_them():
    g = random_map(10, scored=False)
    with pytest.raises(BudgetError, match="gsc score"):
        strategy_scores(g, "pwas")
    with pytest.raises(BudgetError, match="alpha"):
        strategy_scores(g, "alpha-t")
    with pytest.raises(InputError, match="unknown strategy"):
        strategy_scores(g, "size")


@pytest.mark.parametrize("seed", [-1, 1.5, True])
def test_a_bad_seed_is_an_input_error_not_numpys(seed):
    # library callers reach here without the CLI's IntRange check
    with pytest.raises(InputError, match="seed must be an integer >= 0"):
        select_top(random_map(10), 0.5, "random", seed=seed)


def test_refinement_checks_its_seed_before_anything_else():
    from gscompress.ops.refine import refine
    from gscompress.slam.config import resolve_config

    with pytest.raises(InputError, match="seed must be an integer >= 0"):
        refine(random_map(10), [], None, resolve_config("tiny"), 0, seed=-3)  # type: ignore[arg-type]


@pytest.mark.parametrize("strategy", ["pwas", "alpha-t", "opacity", "random"])
def test_an_empty_map_is_said_to_be_empty(strategy):
    with pytest.raises(BudgetError, match="the map is empty"):
        strategy_scores(random_map(0), strategy)
