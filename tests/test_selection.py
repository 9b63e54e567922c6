"""Budgeted selection: exact counts, top of the score, deterministic ties, never over budget."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscompress.errors import BudgetError, InputError
from gscompress.gaussians import random_map
from gscompress.selection import (
    Ranking,
    keep_count,
    select_count,
    select_top,
    spread_ranks,
    strategy_scores,
    top_index,
    top_k,
)


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


@given(
    scores=st.lists(st.integers(0, 5), min_size=2, max_size=60),  # small range: many ties
    counts=st.lists(st.integers(0, 60), min_size=1, max_size=8),
    seed=st.integers(0, 1000),
    special=st.sampled_from([None, -0.0, float("nan")]),
)
def test_a_ranking_gives_top_index_for_every_count(scores, counts, seed, special):
    """`Ranking.top` (the scores sorted once) keeps what `top_index` keeps, count after count,
    ties, zeros of either sign and NaN included; and with a preferred set (`first`)."""
    rng = np.random.default_rng(seed)
    n = len(scores)
    g = random_map(n, seed)
    g.ids = rng.permutation(n).astype(np.uint32)
    values = np.asarray(scores, dtype=np.float64)
    if special is not None:
        values[rng.random(n) < 0.3] = special
    first = rng.random(n) < 0.3
    plain, preferring = Ranking(g, values), Ranking(g, values, first)
    for k in [min(c, n) for c in counts] * 2:
        np.testing.assert_array_equal(plain.top(k), top_index(g, k, values))
        np.testing.assert_array_equal(preferring.top(k), top_index(g, k, values, first))


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


def test_a_spread_selection_takes_each_place_once_before_any_twice():
    """Ten high scores crowd one corner, four low ones lie far apart: the spread order takes
    the crowd's best, then every far one, before a second of the crowd."""
    rng = np.random.default_rng(0)
    crowd = rng.normal(0.0, 0.01, (10, 3))
    far = np.array([[3.0, 0, 0], [0, 3.0, 0], [0, 0, 3.0], [3.0, 3.0, 3.0]])
    scores = np.r_[np.linspace(10.0, 20.0, 10), [1.0, 2.0, 3.0, 4.0]]
    ids = np.arange(14)
    ranks = spread_ranks(scores, ids, np.r_[crowd, far])
    assert sorted(ranks) == list(range(14))
    order = np.argsort(ranks)
    assert order[0] == 9  # the crowd's best
    assert set(order[1:5]) == {10, 11, 12, 13}  # then each far place
    assert list(order[5:]) == list(np.argsort(-scores[:9]))  # then the crowd by score
    # plain top-k of the same scores would take the crowd only
    assert set(top_k(scores, ids, 5)) == {5, 6, 7, 8, 9}


def test_spread_ranks_follow_the_scores_where_nothing_crowds_or_all_coincide():
    g = random_map(300, seed=5)
    scores = strategy_scores(g, "pwas")
    at_one_place = np.zeros((300, 3))
    assert list(np.argsort(spread_ranks(scores, g.ids, at_one_place))) == list(
        np.lexsort((g.ids, -scores))
    )
    # a larger selection keeps every Gaussian a smaller one kept (the grids nest)
    ranks = spread_ranks(scores, g.ids, g.means)
    kept = [set(np.flatnonzero(ranks < k)) for k in (10, 50, 200)]
    assert kept[0] <= kept[1] <= kept[2]
    spread, index = select_count(g, 50, "pwas", spread=True)
    assert set(index) == kept[1] and len(spread) == 50


def test_a_spread_share_records_it_and_sends_the_places_a_plain_one_leaves(tmp_path):
    from dataclasses import replace

    from gscompress.io.mcap_log import LogMetadata, LogReader
    from gscompress.io.ply import write_ply
    from gscompress.pipeline.share import share_log
    from gscompress.pipeline.share.options import ShareOptions

    g = random_map(200, seed=6)
    means = g.means.copy()
    means[:150] = means[:150] * 0.001  # 150 crowd the origin
    sums = g.importance_sum.copy()
    sums[:150] += 100.0 * g.importance_weight[:150]  # and hold the highest scores
    g = replace(g, means=means, importance_sum=sums)
    assert g.importance[:150].min() > g.importance[150:].max()
    src = tmp_path / "src.ply"
    write_ply(g, src)
    plain = share_log(
        src, tmp_path / "plain.mcap", 0.2, ShareOptions(ids=True), source=(g, LogMetadata())
    )
    spread = share_log(
        src,
        tmp_path / "spread.mcap",
        0.2,
        ShareOptions(spread=True, ids=True),
        source=(g, LogMetadata()),
    )  # (the ids say which were sent)
    assert spread["spread"] is True and "spread" not in plain
    sent = {}
    for name in ("plain", "spread"):
        with LogReader(tmp_path / f"{name}.mcap") as log:
            sent[name] = set(log.read_map().ids.tolist())
            operation = log.metadata.provenance[-1]["operation"]
            assert operation.get("spread", False) is (name == "spread")
    outside = set(g.ids[150:].tolist())
    assert not sent["plain"] & outside and len(sent["spread"] & outside) > 20
