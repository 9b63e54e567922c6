"""results.md: an experiment's tables (Table 3, Table 4, the rate-distortion sweep, PWAS
against each strategy, the cross-agent scores, the alignment) in Markdown, with its plots."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from gscompress import __version__
from gscompress.pipeline.experiment.cross_agent import FRAME_SETS
from gscompress.pipeline.experiment.protocol import (
    AGENT_ROWS,
    TRUE_TRANSFORM_ROW,
    ExperimentSettings,
    protocol_of,
)
from gscompress.pipeline.experiment.results import (
    TIE_DB,
    curve_at,
    mean_of,
    quality_key,
    rate_distortion_curves,
    sweep_rows,
)


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


def results_markdown(
    seq: Path,
    s: ExperimentSettings,
    rows: list[dict[str, Any]],
    verdicts: dict[str, Any],
    plots: list[Path],
    out: Path,
) -> str:
    """results.md of an experiment on `seq` (`plots`: the plots written, linked relative to
    `out`)."""
    lines = _head_lines(seq, s, rows) + _table3_lines(rows) + _table4_lines(rows, s, verdicts)
    lines += _sweep_lines(rows, s, verdicts)
    lines += _cell_lines(verdicts["cells"], s)
    if s.refine_poses:
        lines += _cross_lines(rows, s)
    if s.anchor == "own":
        lines += _alignment_lines(rows, s)
    lines += _plot_lines(s, plots, out)
    return "\n".join(lines) + "\n"


def _head_lines(seq: Path, s: ExperimentSettings, rows: list[dict[str, Any]]) -> list[str]:
    """results.md's title and what was run: the frames of each agent, how B receives a share,
    the settings and how the runs were scored."""
    frames_a, frames_b = (
        next((r["frames"] for r in rows if r["name"] == name), "?") for name in AGENT_ROWS[s.split]
    )
    return [
        f"# gsc experiment: {seq.name}",
        "",
        f"Frames `{s.frames}` (A: `{frames_a}`, B: `{frames_b}`); "
        + _receive_text(s)
        + f"Preset `{s.preset}`"
        + (f" + `{s.config_path}`" if s.config_path else "")
        + f", keep {s.keep}, budget {s.budget}, seeds {s.seeds}, evaluated every {s.every} "
        "frame(s) of each run's own frames at its estimated poses (PSNR/SSIM on valid-depth "
        "pixels; ATE RMSE after SE(3) alignment, cm). gscompress " + __version__ + ".",
    ]


def _table3_lines(rows: list[dict[str, Any]]) -> list[str]:
    """results.md's Table 3: the runs over the whole sequence, pruned or not."""
    lines = [
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
    return lines


def _table4_lines(
    rows: list[dict[str, Any]], s: ExperimentSettings, verdicts: dict[str, Any]
) -> list[str]:
    """results.md's Table 4: B with each share at the budget, per seed and on average, and
    whether PWAS beats random."""
    split = (
        "B maps the even frames, A the odd ones"
        if s.split == "odd-even"
        else f"A maps the first part of the frames, B the last, overlapping by {s.overlap:g}"
    )
    lines = [
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
    lines += [
        "",
        f"Mean over {s.seeds} seed(s):",
        "",
        "| Method | ATE RMSE (cm) | PSNR | SSIM | LPIPS | Gaussians | Bytes shared |",
        "|---|---|---|---|---|---|---|",
    ]
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
    ]
    return lines


def _sweep_lines(
    rows: list[dict[str, Any]], s: ExperimentSettings, verdicts: dict[str, Any]
) -> list[str]:
    """results.md's rate-distortion section: each strategy at each budget of the sweep, the
    points of the field (`_reference_lines`) and PWAS minus random paired by seed."""
    v = verdicts
    lines = ["", "## Rate-distortion (B with A's share, mean over the sweep seeds)", ""]
    if s.sweep_seeds == 0:
        lines.append("No sweep was run (`--sweep-seeds 0`).")
    else:
        lines += [
            f"PSNR: {_psnr_text(s)}.",
            "",
            "| Budget | Strategy | PSNR | ATE RMSE (cm) | Gaussians shared | Bytes shared |",
            "|---|---|---|---|---|---|",
        ]
    for budget in s.sweep:  # no rows without sweep seeds (sweep_rows)
        for strategy in s.strategies:
            group = sweep_rows(rows, s, budget, strategy)
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
                b["budget"],
                b["pairs"],
                _plus_minus(b["psnr_difference"], b["psnr_difference_se"], ".2f"),
                f"{b['pwas_higher_psnr']} of {b['pairs']}",
            ]
            if inject:
                cells += [
                    _plus_minus(b["ate_difference_cm"], b["ate_difference_se_cm"], ".3f"),
                    f"{b['pwas_lower_ate']} of {b['pairs']}",
                ]
            lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return lines


def _plot_lines(s: ExperimentSettings, plots: list[Path], out: Path) -> list[str]:
    """results.md's plots, linked relative to `out`."""
    lines = ["", "## Plots", ""]
    if s.mode == "merge" and s.sweep_seeds:
        lines += [
            "The rate-distortion plot shows PSNR alone: a merge leaves B's poses as they were, "
            "so B's ATE cannot vary with the share (run `--mode inject` for an ATE curve). "
            "Each plot is also written as an SVG beside its PNG.",
            "",
        ]
    return lines + [f"![{p.stem}]({p.relative_to(out)})" for p in plots]


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
        "",
        "A's whole map, sent whole (mean over the sweep seeds): as our compact share, and as "
        "the field's formats send it (`gscompress.pipeline.share.formats.format_share`: fp32 "
        "in our fp32 codec; SPZ and SOG, which keep no ids or PWAS sums, written and read back), "
        "each received by B like a share. The last column reads the PWAS curve at the same bytes, "
        "linear in log(bytes) between the two sweep budgets around it (n/a outside the sweep).",
        "",
        "| A's whole map as | Gaussians | Bytes | Bytes per Gaussian | PSNR | PWAS share at "
        "these bytes |",
        "|---|---|---|---|---|---|",
    ]
    for name in ("full", *s.references):
        point = curves.get(name)
        label = "compact (our share)" if name == "full" else name
        if not point:
            why = (
                "not measured: splat-transform was not found (`make js-deps` installs it)"
                if name == "sog" and splat_transform() is None
                else "not measured (see the failed runs)"
            )
            lines.append(f"| {label} | {why} | | | | |")
            continue
        size, psnr, _ = point[0]
        group = [
            r
            for r in rows
            if r["strategy"] == name and r["seed"] is not None and r["seed"] < s.sweep_seeds
        ]
        count = mean_of([r["share_gaussians"] for r in group])
        per = size / count if count else None
        at = curve_at(curves.get("pwas", []), size)
        lines.append(
            f"| {label} | {_fmt(count, '.0f')} | {size:.0f} | {_fmt(per, '.2f')} | "
            f"{_fmt(psnr)} | {_fmt(at)} |"
        )
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
        est = next(
            (
                r
                for r in rows
                if r["seed"] == seed
                and r["table"] == "table4"
                and r["name"] == f"B + pwas {s.budget}"
            ),
            None,
        )
        true = next(
            (
                r
                for r in rows
                if r["seed"] == seed and r["name"] == f"{TRUE_TRANSFORM_ROW} {s.budget}"
            ),
            None,
        )
        if est is None or true is None:
            continue
        diff = None if est["psnr"] is None or true["psnr"] is None else est["psnr"] - true["psnr"]
        lines.append(
            f"| {seed} | {_fmt(est['align_error_cm'])} | {_fmt(est['align_error_deg'])} | "
            f"{_fmt(est['psnr'])} | {_fmt(true['psnr'])} | {_fmt(diff)} | "
            f"{est['align_refused'] or 'no'} |"
        )
    lines += [
        "",
        "Each alignment's figures (overlap, residual, inliers, the drift that local "
        "refinement finds from the true transform, a refusal; under `on_frames` the "
        "registration's error before B's frames refined it, and the drift those frames "
        "find) are in runs/s*_align.json; "
        "a refused alignment's estimate is still merged, and counts as a miss.",
    ]
    return lines
