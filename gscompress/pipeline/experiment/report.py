"""What an experiment reports: results rows, the PWAS-against-random verdicts, tables
(results.md, results.csv, results.json) and plots."""

from __future__ import annotations

import csv
import itertools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gscompress import __version__
from gscompress.io.files import json_text, write_atomic, write_text_atomic
from gscompress.io.mcap_log import LogReader
from gscompress.pipeline.experiment.cross_agent import FRAME_SETS
from gscompress.pipeline.experiment.protocol import (
    AGENT_ROWS,
    B_NO_SHARE,
    FOR_B,
    REFERENCE_TABLE,
    RESCORED,
    TRUE_TRANSFORM_ROW,
    ExperimentSettings,
    RunHandle,
    protocol_of,
    same_budget,
)
from gscompress.pipeline.info import log_edges
from gscompress.selection import strategy_scores

TIE_DB = 0.005
"""Two PSNRs closer than this (they print alike at 0.01 dB) are a tie, counted apart."""

CROSS_KEYS = ("refined_psnr", "pose_change_cm", "pose_change_deg", "start_psnr")
"""Per frame set (`FRAME_SETS`), the cross-agent columns of a results row."""


ROW_KEYS = (
    "name", "table", "seed", "strategy", "budget", "frames", "ate_rmse_cm", "ate_splatam_cm",
    "ate_reason", "psnr", "ssim", "ms_ssim", "lpips", "depth_l1_cm", "gaussians", "bytes",
    "share_gaussians", "share_bytes", "seconds_per_frame", "log", "error", "align_error_cm",
    "align_error_deg", "align_refused", "refine_iters",
    *(f"{key}_{name}" for name in FRAME_SETS for key in CROSS_KEYS),
)  # fmt: skip
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
        name=name, table=table, seed=seed, strategy=strategy, budget=budget,
        frames=ev.get("frames"), seconds_per_frame=slam.get("seconds_per_frame"),
        share_gaussians=got.get("selected"),
        share_bytes=got.get("file_bytes", got.get("bytes")),  # (what crosses the link)
        log=None if error else f"runs/{run.path.name}", error=error,
    )  # fmt: skip
    if align is not None and align.error is None:
        row.update(align_error_cm=align.result["error_cm"],
                   align_error_deg=align.result["error_deg"],
                   align_refused=align.result["refused"])  # fmt: skip
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
    lines = ["", "## Failed runs", "",
             f"{len(runs)} run(s) failed (after one retry) or were not run; a rerun redoes them.",
             "", "| Run | Error |", "|---|---|"]  # fmt: skip
    for name, error in sorted(runs.items()):
        first = error.split("\n", 1)[0].replace("|", "\\|")
        lines.append(f"| {name} | {first} |")
    return lines


def quality_key(s: ExperimentSettings) -> str:
    """The PSNR column that ranks the shares: all frames at refined poses (what B with a share
    gains on A's places as well as its own), or, with `refine_poses` 0, B's own frames at its
    estimated poses."""
    return "refined_psnr_all" if s.refine_poses else "psnr"


def _sweep_rows(
    rows: list[dict[str, Any]], s: ExperimentSettings, budget: str, strategy: str | None = None
) -> list[dict]:
    """Rows of B with a share at `budget` on the sweep seeds (the main budget's included), of
    one strategy or (None) of every compared one."""
    return [
        r for r in rows
        if r["table"] in ("table4", "sweep")
        and (r["strategy"] == strategy if strategy else r["strategy"] in s.strategies)
        and r["seed"] is not None and r["seed"] < s.sweep_seeds
        and same_budget(r["budget"], budget)
    ]  # fmt: skip


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
        groups = [_sweep_rows(rows, s, budget, strategy) for budget in s.sweep]
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
    group = [r for b in s.sweep for r in _sweep_rows(rows, s, b)]
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
                table, strategy, budget, seed,
            ):  # fmt: skip
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
        per_seed.append({"seed": seed, "pwas_beats_random_psnr": psnr_win,
                         "pwas_beats_random_ate": ate_win})  # fmt: skip
    sweep = []
    for budget in s.sweep:
        group = _sweep_rows(rows, s, budget)
        mp = mean_of([r[key] for r in group if r["strategy"] == "pwas"])
        mr = mean_of([r[key] for r in group if r["strategy"] == "random"])
        if mp is None or mr is None:
            continue
        psnr = paired_difference(group, key)
        ate = paired_difference(group, "ate_rmse_cm")
        sweep.append({"budget": budget, "pwas_psnr": mp, "random_psnr": mr,
                      "pwas_at_or_above_random": mp >= mr, "pairs": psnr["pairs"],
                      "psnr_difference": psnr["mean"], "psnr_difference_se": psnr["se"],
                      "pwas_higher_psnr": psnr["positive"],
                      "ate_difference_cm": ate["mean"], "ate_difference_se_cm": ate["se"],
                      "pwas_lower_ate": ate["negative"]})  # fmt: skip
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


def _fmt(value: Any, spec: str = ".2f") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return format(value, spec)


def _mean_cell(group: list[dict[str, Any]], key: str, spec: str = ".2f") -> str:
    """The mean of `key` over a group of rows, formatted for a table (n/a without values)."""
    return _fmt(mean_of([r[key] for r in group]), spec)


def _plus_minus(mean: float | None, se: float | None, spec: str) -> str:
    """`mean ± se` (`mean` alone without a standard error; n/a without a mean)."""
    if mean is None or se is None:
        return _fmt(mean, "+" + spec)
    return f"{mean:+{spec}} ± {se:{spec}}"


def write_reports(
    out: Path,
    seq: Path,
    s: ExperimentSettings,
    rows: list[dict[str, Any]],
    verdicts: dict[str, Any],
    full_log: Path | None,
    failed: dict[str, str] | None = None,
) -> dict[str, str]:
    """results.json, results.csv, results.md and plots/*.png; `full_log`: Table 3's unpruned
    run (None: it failed, and the importance plots are left out); `failed`: the name and
    error of each run that failed."""
    write_text_atomic(out / "results.json", json_text(rows, indent=1))
    write_text_atomic(out / "results.csv", _csv(rows))
    plots = _plots(out / "plots", rows, s, full_log, seq)
    text = _markdown(seq, s, rows, verdicts, plots, out)
    text += "".join(line + "\n" for line in failed_runs(failed or {}))
    write_text_atomic(out / "results.md", text)
    return {
        "results_md": str(out / "results.md"),
        "results_csv": str(out / "results.csv"),
        "results_json": str(out / "results.json"),
        "plots": ", ".join(str(p) for p in plots),
    }


def _csv(rows: list[dict[str, Any]]) -> str:
    import io

    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=ROW_KEYS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in ROW_KEYS})
    return buffer.getvalue()


PROTOCOL_TEXT = {
    "commands": "Protocol `commands`: each share and merge as `gsc share` and `gsc merge` make "
    "them by default (`--protocol paper` runs the paper's exact protocol). ",
    "paper": "Protocol `paper`: the paper's exact protocol (`--protocol paper`: top-K shares, "
    "nothing folded; the exact merge), not what `gsc share` and `gsc merge` do by default. ",
    "custom": "Protocol: custom (neither `gsc share` and `gsc merge`'s defaults nor the "
    "paper's exact protocol). ",
}
"""How results.md names the experiment's protocol (`protocol_of`)."""


def _receive_text(s: ExperimentSettings) -> str:
    shares = PROTOCOL_TEXT[protocol_of(s.fold, s.merge_how)] + (
        (
            "Each share folds what it leaves out into what it sends. "
            if s.fold
            else "Each share is the top K of its strategy, nothing folded. "
        )
        + ("Every strategy's order is spread over space (`--spread`). " if s.spread else "")
        + ("The shares carry no PWAS sums (`--no-sums`). " if not s.sums else "")
        + ("The shares carry the Gaussians' ids (`--ids`). " if s.ids else "")
    )
    if s.mode == "inject":
        return shares + "B's run starts with the share injected. "
    how = (
        "the exact merge: every Gaussian of both maps"
        if s.merge_how == "exact"
        else "`gsc merge`'s default: the share aligned, the surfaces both maps hold resolved"
    )
    return shares + (
        f"B merges a share into its map ({how}) and refines it ({s.merge_iters} iterations on "
        f"its {s.merge_views}, the learning rates decaying to {s.merge_lr_final:g} of their "
        "start; B's poses, so its ATE, do not change). "
    )


def _markdown(
    seq: Path,
    s: ExperimentSettings,
    rows: list[dict[str, Any]],
    verdicts: dict[str, Any],
    plots: list[Path],
    out: Path,
) -> str:
    frames_a, frames_b = (
        next((r["frames"] for r in rows if r["name"] == name), "?") for name in AGENT_ROWS[s.split]
    )
    split = (
        "B maps the even frames, A the odd ones"
        if s.split == "odd-even"
        else f"A maps the first part of the frames, B the last, overlapping by {s.overlap:g}"
    )
    lines = [
        f"# gsc experiment: {seq.name}",
        "",
        f"Frames `{s.frames}` (A: `{frames_a}`, B: `{frames_b}`); "
        + _receive_text(s)
        + f"Preset `{s.preset}`"
        + (f" + `{s.config_path}`" if s.config_path else "")
        + f", keep {s.keep}, budget {s.budget}, seeds {s.seeds}, evaluated every {s.every} "
        "frame(s) of each run's own frames at its estimated poses (PSNR/SSIM on valid-depth "
        "pixels; ATE RMSE after SE(3) alignment, cm). gscompress " + __version__ + ".",
        "",
        "## Table 3: PWAS pruning over the whole sequence",
        "",
        "| Method | Gaussians | Reduction | PSNR | SSIM | LPIPS | ATE RMSE (cm) |",
        "|---|---|---|---|---|---|---|",
    ]
    t3 = [r for r in rows if r["table"] == "table3"]
    base = t3[0]["gaussians"] or 1
    for r in t3:
        reduction = 100.0 * (1 - (r["gaussians"] or 0) / base)
        lines.append(
            f"| {r['name']} | {r['gaussians']} | {reduction:.1f}% | {_fmt(r['psnr'])} | "
            f"{_fmt(r['ssim'], '.3f')} | {_fmt(r['lpips'], '.3f')} | "
            f"{_fmt(r['ate_rmse_cm'], '.3f')} |"
        )
    lines += [
        "",
        f"## Table 4: sharing at budget {s.budget} ({split})",
        "",
        "| Seed | Method | ATE RMSE (cm) | PSNR | SSIM | LPIPS | Gaussians | Shared "
        "| Bytes shared |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    t4 = [r for r in rows if r["table"] == "table4"]
    for r in t4:
        lines.append(
            f"| {r['seed']} | {r['name']} | {_fmt(r['ate_rmse_cm'], '.3f')} | {_fmt(r['psnr'])} | "
            f"{_fmt(r['ssim'], '.3f')} | {_fmt(r['lpips'], '.3f')} | {r['gaussians']} | "
            f"{_fmt(r['share_gaussians'], 'd')} | {_fmt(r['share_bytes'], 'd')} |"
        )
    lines += ["", f"Mean over {s.seeds} seed(s):", "",
              "| Method | ATE RMSE (cm) | PSNR | SSIM | LPIPS | Gaussians | Bytes shared |",
              "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name in dict.fromkeys(r["name"] for r in t4):
        group = [r for r in t4 if r["name"] == name]
        lines.append(
            f"| {name} | {_mean_cell(group, 'ate_rmse_cm', '.3f')} | {_mean_cell(group, 'psnr')} "
            f"| {_mean_cell(group, 'ssim', '.3f')} | {_mean_cell(group, 'lpips', '.3f')} | "
            f"{_mean_cell(group, 'gaussians', '.0f')} | {_mean_cell(group, 'share_bytes', '.0f')} |"
        )
    v = verdicts
    ate_text = (
        "ATE: a merge leaves B's poses as they were (compare ATE with --mode inject)."
        if s.mode == "merge"
        else f"On ATE in {v['pwas_beats_random_ate']} of {s.seeds}."
    )
    lines += [
        "",
        f"PWAS beats random at {s.budget}: on PSNR ({_psnr_text(s)}) in "
        f"{v['pwas_beats_random_psnr']} of {s.seeds} seed(s). {ate_text}",
        "",
        "## Rate-distortion (B with A's share, mean over the sweep seeds)",
        "",
    ]
    if s.sweep_seeds == 0:
        lines.append("No sweep was run (`--sweep-seeds 0`).")
    else:
        lines += [
            f"PSNR: {_psnr_text(s)}.",
            "",
            "| Budget | Strategy | PSNR | ATE RMSE (cm) | Gaussians shared | Bytes shared |",
            "|---|---|---|---|---|---|",
        ]
    for budget in s.sweep:  # no rows without sweep seeds (_sweep_rows)
        for strategy in s.strategies:
            group = _sweep_rows(rows, s, budget, strategy)
            if group:
                lines.append(
                    f"| {budget} | {strategy} | {_mean_cell(group, quality_key(s))} | "
                    f"{_mean_cell(group, 'ate_rmse_cm', '.3f')} | "
                    f"{_mean_cell(group, 'share_gaussians', '.0f')} | "
                    f"{_mean_cell(group, 'share_bytes', '.0f')} |"
                )
    lines += _reference_lines(rows, s)
    if v["sweep"]:
        inject = s.mode == "inject"
        lines += [
            "",
            "PWAS minus random, paired by seed (mean ± standard error over the seeds; a mean "
            "within about two standard errors of 0 is not resolved by this many seeds):",
            "",
            "| Budget | Seeds | PSNR (dB) | PWAS higher |"
            + (" ATE RMSE (cm) | PWAS lower |" if inject else ""),
            "|---|---|---|---|" + ("---|---|" if inject else ""),
        ]
        for b in v["sweep"]:
            cells = [
                b["budget"], b["pairs"],
                _plus_minus(b["psnr_difference"], b["psnr_difference_se"], ".2f"),
                f"{b['pwas_higher_psnr']} of {b['pairs']}",
            ]  # fmt: skip
            if inject:
                cells += [
                    _plus_minus(b["ate_difference_cm"], b["ate_difference_se_cm"], ".3f"),
                    f"{b['pwas_lower_ate']} of {b['pairs']}",
                ]
            lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    lines += _cell_lines(v["cells"], s)
    if s.refine_poses:
        lines += _cross_lines(rows, s)
    if s.anchor == "own":
        lines += _alignment_lines(rows, s)
    lines += ["", "## Plots", ""]
    if s.mode == "merge" and s.sweep_seeds:
        lines += [
            "The rate-distortion plot shows PSNR alone: a merge leaves B's poses as they were, "
            "so B's ATE cannot vary with the share (run `--mode inject` for an ATE curve). "
            "Each plot is also written as an SVG beside its PNG.",
            "",
        ]
    lines += [f"![{p.stem}]({p.relative_to(out)})" for p in plots]
    return "\n".join(lines) + "\n"


PLOT_DPI = 200
"""Resolution of the PNG plots (an SVG of each is written beside it)."""


def _psnr_text(s: ExperimentSettings) -> str:
    """What the PSNR that ranks the shares (`quality_key`) is, in words."""
    if s.refine_poses:
        return f"all frames, each pose refined against the map ({s.refine_poses} iterations)"
    return "B's own frames at B's estimated poses"


def _reference_lines(rows: list[dict[str, Any]], s: ExperimentSettings) -> list[str]:
    """results.md's points of the field: B with A's whole map in our compact share and in each
    reference format, beside the PWAS curve read at the same bytes (`curve_at`)."""
    if not s.references or not s.sweep_seeds:
        return []
    from gscompress.io.sog import splat_transform

    curves = rate_distortion_curves(rows, s)
    lines = [
        "", "A's whole map, sent whole (mean over the sweep seeds): as our compact share, and as "
        "the field's formats send it (`gscompress.pipeline.share.formats.format_share`: fp32 "
        "in our fp32 codec; SPZ and SOG, which keep no ids or PWAS sums, written and read back), "
        "each received by B like a share. The last column reads the PWAS curve at the same bytes, "
        "linear in log(bytes) between the two sweep budgets around it (n/a outside the sweep).",
        "", "| A's whole map as | Gaussians | Bytes | Bytes per Gaussian | PSNR | PWAS share at "
        "these bytes |", "|---|---|---|---|---|---|",
    ]  # fmt: skip
    for name in ("full", *s.references):
        point = curves.get(name)
        label = "compact (our share)" if name == "full" else name
        if not point:
            why = ("not measured: splat-transform was not found (`make js-deps` installs it)"
                   if name == "sog" and splat_transform() is None
                   else "not measured (see the failed runs)")  # fmt: skip
            lines.append(f"| {label} | {why} | | | | |")
            continue
        size, psnr, _ = point[0]
        group = [r for r in rows if r["strategy"] == name and r["seed"] is not None
                 and r["seed"] < s.sweep_seeds]  # fmt: skip
        count = mean_of([r["share_gaussians"] for r in group])
        per = size / count if count else None
        at = curve_at(curves.get("pwas", []), size)
        lines.append(f"| {label} | {_fmt(count, '.0f')} | {size:.0f} | {_fmt(per, '.2f')} | "
                     f"{_fmt(psnr)} | {_fmt(at)} |")  # fmt: skip
    return lines


def _cell_lines(cells: dict[str, Any], s: ExperimentSettings) -> list[str]:
    """results.md's count of PWAS against each other strategy, cell by cell (`pwas_cells`)."""
    if not cells["cells"]:
        return []
    n = cells["cells"]
    lines = [
        "",
        "## PWAS against each strategy, cell by cell",
        "",
        f"Each (seed, budget) of the sweep where every strategy was scored ({n} cells; PSNR: "
        f"{_psnr_text(s)}). PWAS is at or above every other strategy (its ablations aside: "
        "PWAS scored again, e.g. without the proximity weight) in "
        f"{cells['at_or_above']} of {n} cells ({100 * cells['at_or_above'] / n:.0f}%), above "
        f"every one by more than {TIE_DB:g} dB in {cells['above']}. Against each, PWAS minus "
        "the strategy (mean ± standard error over the cells):",
        "",
        "| Strategy | Cells | PWAS above | Tied | PWAS below | PWAS minus it (dB) |",
        "|---|---|---|---|---|---|",
    ]
    for name, d in cells["against"].items():
        lines.append(
            f"| {name} | {d['pairs']} | {d['above']} | {d['ties']} | {d['below']} | "
            f"{_plus_minus(d['mean'], d['se'], '.2f')} |"
        )
    return lines


def _plot_title(seq: Path, s: ExperimentSettings, what: str, seeds: str) -> str:
    """A plot's title: what it shows, the sequence, the split and the seeds it averages."""
    split = "odd-even" if s.split == "odd-even" else f"halves, overlap {s.overlap:g}"
    return f"{what}\n{seq.name}, split {split}, {s.mode}, {seeds}"


def _cross_lines(rows: list[dict[str, Any]], s: ExperimentSettings) -> list[str]:
    """results.md's table of the cross-agent scores: per row (mean over the seeds), PSNR on A's
    frames, B's frames and all frames at refined poses, with the median pose change."""
    moved = "moved by the estimated alignment, " if s.anchor == "own" else ""
    lines = [
        "",
        f"## PSNR on A's frames / B's frames / all frames, poses refined ({s.refine_poses} "
        "iterations)",
        "",
        "Each map scored on every frame set after refining each frame's pose against the fixed "
        f"map ({s.refine_poses} tracking iterations, `gsc eval --refine-poses`), starting from "
        "the estimated poses of the agent that made the map on its own frames, the other "
        f"agent's ({moved}as `gsc eval --poses-from`) on the other's, and on all frames the "
        "map's own poses where it has them, the other agent's on the rest; the centralised run "
        "starts at its own poses everywhere. In brackets: the median pose change (cm). Mean "
        f"over {s.seeds} seed(s), every {s.every} frame(s) of each set.",
        "",
        "| Method | A's frames | B's frames | All frames |",
        "|---|---|---|---|",
    ]
    scored = [r for r in rows if r["refine_iters"] is not None]
    for name in dict.fromkeys(r["name"] for r in scored):
        group = [r for r in scored if r["name"] == name]
        label = f"centralised ({name})" if group[0]["table"] == "table3" else name
        cells = [
            f"{_mean_cell(group, f'refined_psnr_{key}')} "
            f"({_mean_cell(group, f'pose_change_cm_{key}')} cm)"
            for key in FRAME_SETS
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if not scored:
        lines.append("| (no run was scored: see the failed runs) | | | |")
    return lines


def _alignment_lines(rows: list[dict[str, Any]], s: ExperimentSettings) -> list[str]:
    """results.md's section on anchor "own": per seed, the error of the transform from A's
    frame to B's against the true one, and B with the PWAS share at each."""
    lines = [
        "",
        "## Alignment (each agent at the identity at its own first frame)",
        "",
        "`gsc align` of A's map to B's, refined on B's frames (`gsc align --seq`), against the "
        "transform between the agents' ground-truth first poses (the agents' own drift is part "
        "of the error); B's PSNR with the PWAS share "
        f"at {s.budget} merged at the estimated and at the true transform.",
        "",
        "| Seed | Error (cm) | Error (deg) | PSNR, estimated | PSNR, true | Difference (dB) "
        "| Refused |",
        "|---|---|---|---|---|---|---|",
    ]
    for seed in range(s.seeds):
        est = next((r for r in rows if r["seed"] == seed and r["table"] == "table4"
                    and r["name"] == f"B + pwas {s.budget}"), None)  # fmt: skip
        true = next((r for r in rows if r["seed"] == seed
                     and r["name"] == f"{TRUE_TRANSFORM_ROW} {s.budget}"), None)  # fmt: skip
        if est is None or true is None:
            continue
        diff = None if est["psnr"] is None or true["psnr"] is None else est["psnr"] - true["psnr"]
        lines.append(
            f"| {seed} | {_fmt(est['align_error_cm'])} | {_fmt(est['align_error_deg'])} | "
            f"{_fmt(est['psnr'])} | {_fmt(true['psnr'])} | {_fmt(diff)} | "
            f"{est['align_refused'] or 'no'} |"
        )
    lines += ["", "Each alignment's figures (overlap, residual, inliers, the drift that local "
              "refinement finds from the true transform, a refusal; under `on_frames` the "
              "registration's error before B's frames refined it, and the drift those frames "
              "find) are in runs/s*_align.json; "
              "a refused alignment's estimate is still merged, and counts as a miss."]  # fmt: skip
    return lines


_WHOLE_MARKERS = {"full": "*", "fp32": "s", "spz": "D", "sog": "P"}
"""Markers of the one-point curves of A's whole map (ours, and each reference format)."""


def _curve_label(name: str, s: ExperimentSettings) -> str:
    """A rate-distortion curve's legend: a strategy, or A's whole map in a format."""
    if name == "full":
        return "A's whole map (compact)"
    return f"A's whole map as {name.upper()}" if name in s.references else name


def _plot_rate_distortion(
    folder: Path,
    curves: dict[str, list[tuple[float, float | None, float | None]]],
    s: ExperimentSettings,
    seq: Path,
) -> Path:
    """PSNR (and, when a share can move B's poses, ATE) of B against the share's bytes on a log
    axis, one curve per strategy; B without a share is the dashed line every share starts from.
    In merge mode B's poses are fixed, so the ATE panel is left out (results.md says why)."""
    import matplotlib.pyplot as plt

    columns = [(1, "PSNR of B, all frames, poses refined (dB)" if s.refine_poses
                else "PSNR of agent B on its frames (dB)")]  # fmt: skip
    if s.mode == "inject":
        columns.append((2, "ATE RMSE of agent B (cm)"))
    fig, axes = plt.subplots(1, len(columns), figsize=(5.5 * len(columns), 4.2), squeeze=False)
    for ax, (column, label) in zip(axes[0], columns, strict=True):
        baseline = None
        for name, points in curves.items():
            shared = [p for p in points if p[0] > 0 and p[column] is not None]
            baseline = next((p[column] for p in points if p[0] == 0), baseline)
            if not shared:
                continue
            whole = name == "full" or name in s.references
            ax.plot(
                [p[0] for p in shared], [p[column] for p in shared],
                label=_curve_label(name, s),
                **(dict(marker=_WHOLE_MARKERS.get(name, "*"), markersize=11, linestyle="none")
                   if whole else dict(marker="o")),
            )  # fmt: skip
        if baseline is not None:
            ax.axhline(baseline, color="grey", linestyle="--", label="B, no share")
        ax.set_xscale("log")
        ax.set_xlabel("share size (bytes, log scale)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize="small")
        else:  # (every run this panel reads failed: results.md lists them)
            ax.text(0.5, 0.5, "no points: see results.md", ha="center", va="center",
                    transform=ax.transAxes)  # fmt: skip
    seeds = f"mean over seed(s) 0-{s.sweep_seeds - 1}" if s.sweep_seeds > 1 else "seed 0"
    fig.suptitle(_plot_title(seq, s, "Rate-distortion: agent B with A's share", seeds),
                 fontsize="medium")  # fmt: skip
    fig.tight_layout()
    return _save(fig, folder / "rate_distortion.png")


def _plots(
    folder: Path,
    rows: list[dict[str, Any]],
    s: ExperimentSettings,
    full_log: Path | None,
    seq: Path,
) -> list[Path]:
    """Rate-distortion curves, importance histogram and top-down importance map (PNG + SVG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    folder.mkdir(parents=True, exist_ok=True)
    paths = []

    curves = rate_distortion_curves(rows, s)
    if curves:  # none without a sweep (--sweep-seeds 0)
        paths.append(_plot_rate_distortion(folder, curves, s, seq))
    if full_log is None:
        return paths

    with LogReader(full_log) as reader:
        gaussians = reader.read_map()
    scores = strategy_scores(gaussians, "pwas")
    assert s.keep is not None  # resolved from the config by run_experiment
    kept = np.sort(scores)[::-1][: max(1, round(s.keep * len(scores)))]
    run = "Table 3's unpruned run (seed 0)"
    fig, ax = plt.subplots(figsize=(6, 4.2))
    positive = scores[scores > 0]
    bins = list(log_edges(positive, 49))
    ax.hist(positive, bins=bins, alpha=0.6, label=f"all ({len(scores)})")
    ax.hist(kept[kept > 0], bins=bins, alpha=0.6, label=f"kept at {s.keep:g} ({len(kept)})")
    ax.set_xscale("log")
    ax.set_xlabel("PWAS importance S / (W + eps) (log scale)")
    ax.set_ylabel("Gaussians (count)")
    ax.legend(fontsize="small")
    fig.suptitle(_plot_title(seq, s, "PWAS importance before and after pruning", run),
                 fontsize="medium")  # fmt: skip
    fig.tight_layout()
    paths.append(_save(fig, folder / "importance_hist.png"))

    plan = _plan_view(gaussians.means)
    fig, ax = plt.subplots(figsize=(6.4, 6))
    order = np.argsort(scores)  # the most important drawn last, on top
    shown = positive.size > 0
    low, high = (positive.min(), positive.max()) if shown else (1e-12, 1.0)
    dots = ax.scatter(
        plan[order, 0], plan[order, 1], c=np.maximum(scores[order], low), s=1, cmap="viridis",
        norm=LogNorm(low, max(high, low * (1 + 1e-9))),
    )  # fmt: skip
    fig.colorbar(dots, ax=ax, label="PWAS importance (log scale)")
    ax.set_aspect("equal")
    ax.set_xlabel("first principal axis of the map (m)")
    ax.set_ylabel("second principal axis of the map (m)")
    fig.suptitle(_plot_title(seq, s, "Top-down view of the map coloured by importance", run),
                 fontsize="medium")  # fmt: skip
    fig.tight_layout()
    paths.append(_save(fig, folder / "importance_topdown.png"))
    return paths


def _plan_view(means: np.ndarray) -> np.ndarray:
    """[N, 2] coordinates on the plane of the two largest principal axes (the floor plan).

    Indoor maps are wider than they are tall, so the axis of least spread is taken as up.
    """
    centred = means - means.mean(axis=0)
    _, _, vt = np.linalg.svd(centred[:: max(1, len(centred) // 20000)], full_matrices=False)
    return centred @ vt[:2].T


def _save(fig: Any, path: Path) -> Path:
    """Write `fig` as a PNG at `PLOT_DPI` and as an SVG beside it; returns the PNG's path."""
    import matplotlib.pyplot as plt

    write_atomic(path, lambda file: fig.savefig(file, format="png", dpi=PLOT_DPI))
    write_atomic(path.with_suffix(".svg"), lambda file: fig.savefig(file, format="svg"))
    plt.close(fig)
    return path
