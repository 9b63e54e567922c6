"""The byte-budget solver of `gsc share --solve`."""

from __future__ import annotations

import itertools

import pytest
from click.testing import CliRunner

from gscompress.errors import BudgetError
from gscompress.io.mcap_log import LogReader, read_map
from gscompress.ops.budget import Budget
from gscompress.pipeline.share.options import ShareOptions
from gscompress.pipeline.share.solve import CANDIDATES, share_solved, solve_share
from gscompress_cli.main import cli

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow


@pytest.mark.parametrize("budget", ["6kB", "10kB", "16kB"])
def test_every_candidate_fits_and_the_best_picture_wins(run, budget):
    best, weighed, record = solve_share(run["log"], Budget.parse(budget), seq=run["seq"])
    assert len(weighed) == len(CANDIDATES) and record["against"] == "frames"
    assert all(c.file_bytes <= Budget.parse(budget).budget_bytes for c in weighed)
    assert best == weighed[0] and all(best.psnr >= c.psnr for c in weighed)
    # within one budget a smaller codec holds more Gaussians, until it holds the whole map
    counts = {(c.codec, c.sums): c.count for c in weighed}
    n = len(read_map(run["log"]))
    order = [
        counts[key]
        for key in (("compact", False), ("compact", True), ("fp16", True), ("fp32", True))
    ]
    assert all(a > b or a == b == n for a, b in itertools.pairwise(order)), (order, n)
    assert order[-1] < n


def test_a_constructed_case_where_fewer_exact_gaussians_win(run):
    """When the budget holds the whole map in fp32, fp32 (lossless) draws the map's own renders
    exactly and must beat the quantised codecs, which draw them a little off."""
    everything = f"{run['log'].stat().st_size * 4}B"
    best, weighed, _ = solve_share(run["log"], Budget.parse(everything))
    n = len(read_map(run["log"]))
    assert all(c.count == n for c in weighed)
    assert best.codec in ("fp32", "fp16") and best.psnr > max(
        c.psnr for c in weighed if c.codec == "compact"
    )


def test_options_constrain_the_search_and_the_share_records_it(run):
    best, weighed, _ = solve_share(
        run["log"],
        Budget.parse("8kB"),
        ShareOptions(codec="compact", sums=True),
        fixed=("codec", "sums"),
    )
    assert best == weighed[0]
    assert sorted((c.codec, c.sums, c.fold) for c in weighed) == [
        ("compact", True, False),
        ("compact", True, True),
    ]
    _, exact, _ = solve_share(
        run["log"],
        Budget.parse("8kB"),
        ShareOptions(codec="compact", fold=False),
        fixed=("codec", "fold"),
    )
    assert sorted((c.sums, c.fold) for c in exact) == [(False, False), (True, False)]
    out = run["root"] / "solve_solved.mcap"
    result = share_solved(run["log"], out, "8kB", seq=run["seq"], force=True)
    assert out.stat().st_size == result["file_bytes"] <= 8000
    with LogReader(out) as reader:
        step = reader.metadata.provenance[-1]["operation"]
    assert step["solve"]["predicted_psnr"] == result["predicted_psnr"]
    assert step["codec"] == result["codec"] and len(step["solve"]["candidates"]) == 8
    with pytest.raises(BudgetError, match="cannot hold one Gaussian"):
        solve_share(run["log"], Budget.parse("2kB"))


def test_share_cli_solves_and_says_so(run):
    out = run["root"] / "solve_cli.mcap"
    args = ["share", str(run["log"]), str(out), "--budget", "6kB", "--solve", "--seq"]
    r = CliRunner().invoke(cli, [*args, str(run["seq"]), "--codec", "fp16"])
    assert r.exit_code == 0, r.output
    assert "solver: fp16" in r.output and "against the frames" in r.output
    assert out.stat().st_size <= 6000
