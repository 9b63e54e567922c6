"""An experiment's plots: the rate-distortion curves, and the importance histogram and top-down
importance map of the unpruned run's map (each a PNG with an SVG beside it)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.files import write_atomic
from gscompress.io.mcap_log import LogReader
from gscompress.pipeline.experiment.protocol import ExperimentSettings
from gscompress.pipeline.experiment.results import rate_distortion_curves
from gscompress.pipeline.info import log_edges
from gscompress.selection import strategy_scores

PLOT_DPI = 200
"""Resolution of the PNG plots (an SVG of each is written beside it)."""


def _plot_title(seq: Path, s: ExperimentSettings, what: str, seeds: str) -> str:
    """A plot's title: what it shows, the sequence, the split and the seeds it averages."""
    split = "odd-even" if s.split == "odd-even" else f"halves, overlap {s.overlap:g}"
    return f"{what}\n{seq.name}, split {split}, {s.mode}, {seeds}"


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

    columns = [
        (
            1,
            "PSNR of B, all frames, poses refined (dB)"
            if s.refine_poses
            else "PSNR of agent B on its frames (dB)",
        )
    ]
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
                [p[0] for p in shared],
                [p[column] for p in shared],
                label=_curve_label(name, s),
                **(
                    dict(marker=_WHOLE_MARKERS.get(name, "*"), markersize=11, linestyle="none")
                    if whole
                    else dict(marker="o")
                ),
            )
        if baseline is not None:
            ax.axhline(baseline, color="grey", linestyle="--", label="B, no share")
        ax.set_xscale("log")
        ax.set_xlabel("share size (bytes, log scale)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize="small")
        else:  # (every run this panel reads failed: results.md lists them)
            ax.text(
                0.5,
                0.5,
                "no points: see results.md",
                ha="center",
                va="center",
                transform=ax.transAxes,
            )
    seeds = f"mean over seed(s) 0-{s.sweep_seeds - 1}" if s.sweep_seeds > 1 else "seed 0"
    fig.suptitle(
        _plot_title(seq, s, "Rate-distortion: agent B with A's share", seeds), fontsize="medium"
    )
    fig.tight_layout()
    return _save(fig, folder / "rate_distortion.png")


def write_plots(
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
    fig.suptitle(
        _plot_title(seq, s, "PWAS importance before and after pruning", run), fontsize="medium"
    )
    fig.tight_layout()
    paths.append(_save(fig, folder / "importance_hist.png"))

    plan = _plan_view(gaussians.means)
    fig, ax = plt.subplots(figsize=(6.4, 6))
    order = np.argsort(scores)  # the most important drawn last, on top
    shown = positive.size > 0
    low, high = (positive.min(), positive.max()) if shown else (1e-12, 1.0)
    dots = ax.scatter(
        plan[order, 0],
        plan[order, 1],
        c=np.maximum(scores[order], low),
        s=1,
        cmap="viridis",
        norm=LogNorm(low, max(high, low * (1 + 1e-9))),
    )
    fig.colorbar(dots, ax=ax, label="PWAS importance (log scale)")
    ax.set_aspect("equal")
    ax.set_xlabel("first principal axis of the map (m)")
    ax.set_ylabel("second principal axis of the map (m)")
    fig.suptitle(
        _plot_title(seq, s, "Top-down view of the map coloured by importance", run),
        fontsize="medium",
    )
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
