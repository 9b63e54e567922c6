"""What an experiment's runs give: results rows, the rate-distortion curves and the
PWAS-against-random verdicts (`gscompress.pipeline.experiment.report` writes them out)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from gscompress.pipeline.experiment.cross_agent import FRAME_SETS
from gscompress.pipeline.experiment.protocol import (
    AGENT_ROWS,
    B_NO_SHARE,
    FOR_B,
    REFERENCE_TABLE,
    RESCORED,
    ExperimentSettings,
    RunHandle,
    same_budget,
)

TIE_DB = 0.005
"""Two PSNRs closer than this (they print alike at 0.01 dB) are a tie, counted apart."""


CROSS_KEYS = ("refined_psnr", "pose_change_cm", "pose_change_deg", "start_psnr")
"""Per frame set (`FRAME_SETS`), the cross-agent columns of a results row."""


ROW_KEYS = (
    "name",
    "table",
    "seed",
    "strategy",
    "budget",
    "frames",
    "ate_rmse_cm",
    "ate_splatam_cm",
    "ate_reason",
    "psnr",
    "ssim",
    "ms_ssim",
    "lpips",
    "depth_l1_cm",
    "gaussians",
    "bytes",
    "share_gaussians",
    "share_bytes",
    "seconds_per_frame",
    "log",
    "error",
    "align_error_cm",
    "align_error_deg",
    "align_refused",
    "refine_iters",
    *(f"{key}_{name}" for name in FRAME_SETS for key in CROSS_KEYS),
)
"""Columns of results.csv (every row of results.json has them). The cross-agent scores
(`cross_agent`) are empty in rows not scored so (and with `refine_poses` 0): `refined_psnr_a`,
`refined_psnr_b`, `refined_psnr_all` (PSNR on A's, B's and all frames at refined poses),
`pose_change_cm_*` and `pose_change_deg_*` (the median pose change from the starting poses),
`start_psnr_*` (PSNR at the starting poses) and `refine_iters` (tracking iterations)."""


def result_row(
    name: str,
    table: str,
    run: RunHandle,
    seed: int | None = None,
    strategy: str = "",
    budget: str = "",
    share: RunHandle | None = None,
    align: RunHandle | None = None,
    cross: RunHandle | None = None,
) -> dict[str, Any]:
    """A results row from a SLAM run's record (and the share it received, moved by the
    transform of `align`, and its cross-agent scoring step `cross`); a run that failed (or was
    not run, a run it needs having failed) gives a row of its error, the rest empty (a scoring
    step that failed leaves its columns empty, and is listed with the failed runs)."""
    error = run.error
    ev, slam = ({}, {}) if error else (run.result["eval"], run.result["slam"])
    got = share.result if share is not None and share.error is None else {}
    row = {key: ev.get(key) for key in ROW_KEYS}
    row.update(
        name=name,
        table=table,
        seed=seed,
        strategy=strategy,
        budget=budget,
        frames=ev.get("frames"),
        seconds_per_frame=slam.get("seconds_per_frame"),
        share_gaussians=got.get("selected"),
        share_bytes=got.get("file_bytes", got.get("bytes")),  # (what crosses the link)
        log=None if error else f"runs/{run.path.name}",
        error=error,
    )
    if align is not None and align.error is None:
        row.update(
            align_error_cm=align.result["error_cm"],
            align_error_deg=align.result["error_deg"],
            align_refused=align.result["refused"],
        )
    if cross is not None and cross.error is None:
        row.update(cross_columns(cross.result["cross"]))
    return row


def cross_columns(scores: dict[str, Any]) -> dict[str, Any]:
    """A row's cross-agent columns from a scoring step's result (`cross_agent.cross_scores`)."""
    row: dict[str, Any] = {}
    for name in FRAME_SETS:
        got = scores[name]
        refined = got["refined"]
        row["refine_iters"] = refined["iters"]
        row[f"refined_psnr_{name}"] = refined["psnr"]
        row[f"pose_change_cm_{name}"] = refined["pose_change_cm"]
        row[f"pose_change_deg_{name}"] = refined["pose_change_deg"]
        row[f"start_psnr_{name}"] = got["psnr"]
    return row


def failed_runs(runs: dict[str, str]) -> list[str]:
    """results.md's lines on the runs that failed: name and first line of the error each."""
    if not runs:
        return []
    lines = [
        "",
        "## Failed runs",
        "",
        f"{len(runs)} run(s) failed (after one retry) or were not run; a rerun redoes them.",
        "",
        "| Run | Error |",
        "|---|---|",
    ]
    for name, error in sorted(runs.items()):
        first = error.split("\n", 1)[0].replace("|", "\\|")
        lines.append(f"| {name} | {first} |")
    return lines


def quality_key(s: ExperimentSettings) -> str:
    """The PSNR column that ranks the shares: all frames at refined poses (what B with a share
    gains on A's places as well as its own), or, with `refine_poses` 0, B's own frames at its
    estimated poses."""
    return "refined_psnr_all" if s.refine_poses else "psnr"


def sweep_rows(
    rows: list[dict[str, Any]], s: ExperimentSettings, budget: str, strategy: str | None = None
) -> list[dict]:
    """Rows of B with a share at `budget` on the sweep seeds (the main budget's included), of
    one strategy or (None) of every compared one."""
    return [
        r
        for r in rows
        if r["table"] in ("table4", "sweep")
        and (r["strategy"] == strategy if strategy else r["strategy"] in s.strategies)
        and r["seed"] is not None
        and r["seed"] < s.sweep_seeds
        and same_budget(r["budget"], budget)
    ]


def rate_distortion_curves(
    rows: list[dict[str, Any]], s: ExperimentSettings
) -> dict[str, list[tuple[float, float | None, float | None]]]:
    """(share bytes, PSNR, ATE cm) of B per strategy over the sweep budgets, means over the
    sweep seeds, sorted by bytes; the PSNR is `quality_key`'s.

    Each strategy's curve starts at B without a share (0 bytes: "B refined, no share" in merge
    mode, B's own run in inject mode), the point every share is a gain over; "full" is the one
    point of A's whole map (our compact share of it), the upper end, and each format of
    `s.references` the one point of A's whole map sent in that format.
    """
    seeds = [r for r in rows if r["seed"] is not None and r["seed"] < s.sweep_seeds]
    reference = B_NO_SHARE if s.mode == "merge" else AGENT_ROWS[s.split][1]
    base = [r for r in seeds if r["name"] == reference]

    key = quality_key(s)

    def point(group: list[dict[str, Any]]) -> tuple[float, float | None, float | None]:
        size = mean_of([r["share_bytes"] or 0 for r in group]) or 0.0
        return size, mean_of([r[key] for r in group]), mean_of([r["ate_rmse_cm"] for r in group])

    curves: dict[str, list[tuple[float, float | None, float | None]]] = {}
    for strategy in s.strategies:
        groups = [sweep_rows(rows, s, budget, strategy) for budget in s.sweep]
        shared = [point(group) for group in groups if group]
        if shared:
            start = [point(base)] if base else []
            curves[strategy] = sorted(start + shared, key=lambda p: p[0])
    full = [r for r in seeds if r["strategy"] == "full"]
    if full and curves:
        curves["full"] = [point(full)]
    for fmt in s.references:
        group = [r for r in seeds if r["table"] == REFERENCE_TABLE and r["strategy"] == fmt]
        if group and curves:
            curves[fmt] = [point(group)]
    return curves


def curve_at(
    points: Sequence[tuple[float, float | None, float | None]], size: float
) -> float | None:
    """A curve's PSNR at `size` bytes, linear in log(bytes) between the two points around it;
    None outside the curve's shares (the 0-byte start is not a share) or without values."""
    shared = [(p[0], p[1]) for p in points if p[0] > 0 and p[1] is not None]
    for (x0, y0), (x1, y1) in itertools.pairwise(shared):
        if x0 <= size <= x1:
            t = 0.0 if x1 == x0 else math.log(size / x0) / math.log(x1 / x0)
            return y0 + t * (y1 - y0)
    return None


def mean_of(values: Sequence[Any]) -> float | None:
    numbers = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(np.mean(numbers)) if numbers else None


def cell_values(group: list[dict[str, Any]], key: str) -> dict[tuple[int, str], dict[str, float]]:
    """Per (seed, budget) cell of `group`'s rows, each strategy's finite value of `key`."""
    cells: dict[tuple[int, str], dict[str, float]] = {}
    for row in group:
        value = row.get(key)
        if value is not None and math.isfinite(value):
            cell = (row["seed"], str(row["budget"]))
            cells.setdefault(cell, {})[row["strategy"]] = float(value)
    return cells


def paired_difference(
    group: list[dict[str, Any]], key: str, other: str = "random"
) -> dict[str, Any]:
    """PWAS minus `other` in `key`, paired by (seed, budget), over the rows of `group`.

    Cells without a finite value for both strategies are left out. Returns the number of pairs,
    the mean difference, its standard error (sample standard deviation / sqrt(pairs); None
    below two pairs), how many differences are positive and negative, and how many of each
    lie beyond `TIE_DB` (`above`, `below`; the rest are `ties`).
    """
    cells = cell_values(group, key).values()
    diffs = np.array([v["pwas"] - v[other] for v in cells if "pwas" in v and other in v])
    n = len(diffs)
    return {
        "pairs": n,
        "mean": float(diffs.mean()) if n else None,
        "se": float(diffs.std(ddof=1) / math.sqrt(n)) if n > 1 else None,
        "positive": int((diffs > 0).sum()),
        "negative": int((diffs < 0).sum()),
        "above": int((diffs > TIE_DB).sum()),
        "below": int((diffs < -TIE_DB).sum()),
        "ties": int((abs(diffs) <= TIE_DB).sum()),
    }


def pwas_cells(rows: list[dict[str, Any]], s: ExperimentSettings) -> dict[str, Any]:
    """PWAS against every other compared strategy, cell by cell: each (seed, budget) of the
    sweep (the sweep seeds, every sweep budget) where all of them were scored, by
    `quality_key`. A cell counts as `at_or_above` when PWAS is above or tied with each other
    strategy but its own ablations (`RESCORED`), `above` when above every one by more than
    `TIE_DB`; `against` pairs PWAS with every other strategy, ablations too."""
    key = quality_key(s)
    others = [name for name in s.strategies if name != "pwas"]
    baselines = [o for o in others if o.removesuffix(FOR_B) not in RESCORED]
    group = [r for b in s.sweep for r in sweep_rows(rows, s, b)]
    cells = cell_values(group, key).values()
    full = [c for c in cells if "pwas" in c and all(o in c for o in baselines)]
    margins = [min(c["pwas"] - c[o] for o in baselines) for c in full] if baselines else []
    return {
        "key": key,
        "cells": len(full),
        "at_or_above": sum(m >= -TIE_DB for m in margins),
        "above": sum(m > TIE_DB for m in margins),
        "against": {o: paired_difference(group, key, o) for o in others},
    }


def verdicts_of(rows: list[dict[str, Any]], s: ExperimentSettings) -> dict[str, Any]:
    """PWAS against random: per seed at the main budget, and per budget in the sweep; and
    against every compared strategy cell by cell (`pwas_cells`). PSNR is `quality_key`'s."""

    def pick(table: str, strategy: str, budget: str, seed: int) -> dict[str, Any] | None:
        for row in rows:
            if (row["table"], row["strategy"], row["budget"], row["seed"]) == (
                table,
                strategy,
                budget,
                seed,
            ):
                return row
        return None

    key = quality_key(s)
    psnr_wins = ate_wins = 0
    per_seed = []
    for seed in range(s.seeds):
        p, r = pick("table4", "pwas", s.budget, seed), pick("table4", "random", s.budget, seed)
        assert p is not None and r is not None
        if p["error"] or r["error"]:  # (in results.md's failed runs)
            continue
        psnr_win = (p[key] or 0) > (r[key] or 0)
        ate_win = (p["ate_rmse_cm"] or math.inf) < (r["ate_rmse_cm"] or math.inf)
        psnr_wins += psnr_win
        ate_wins += ate_win
        per_seed.append(
            {"seed": seed, "pwas_beats_random_psnr": psnr_win, "pwas_beats_random_ate": ate_win}
        )
    sweep = []
    for budget in s.sweep:
        group = sweep_rows(rows, s, budget)
        mp = mean_of([r[key] for r in group if r["strategy"] == "pwas"])
        mr = mean_of([r[key] for r in group if r["strategy"] == "random"])
        if mp is None or mr is None:
            continue
        psnr = paired_difference(group, key)
        ate = paired_difference(group, "ate_rmse_cm")
        sweep.append(
            {
                "budget": budget,
                "pwas_psnr": mp,
                "random_psnr": mr,
                "pwas_at_or_above_random": mp >= mr,
                "pairs": psnr["pairs"],
                "psnr_difference": psnr["mean"],
                "psnr_difference_se": psnr["se"],
                "pwas_higher_psnr": psnr["positive"],
                "ate_difference_cm": ate["mean"],
                "ate_difference_se_cm": ate["se"],
                "pwas_lower_ate": ate["negative"],
            }
        )
    return {
        "budget": s.budget,
        "seeds": s.seeds,
        "mode": s.mode,
        "pwas_beats_random_psnr": psnr_wins,
        "pwas_beats_random_ate": ate_wins,
        "psnr_key": key,
        "per_seed": per_seed,
        "sweep": sweep,
        "cells": pwas_cells(rows, s),
    }
