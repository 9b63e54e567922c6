"""Benchmark the pruning stages (paper Table 3): no pruning vs PWAS vs opacity-only pruning.

For one sequence, runs `gscompress.pipeline.slam_file` three times with the same config except
for the pruning stages: none (`prune.stages: []`), PWAS (`prune.by: pwas`) and opacity-only
(`prune.by: opacity`) at the same `prune.keep`. Each log is evaluated as `gsc eval LOG --seq
SEQ` does (`gscompress.pipeline.evaluate_log`: ATE, and PSNR/SSIM of the final map rendered at
the estimated poses against every training view; LPIPS is skipped for time).

Writes into `--out`/NAME/: the logs and configs of the runs, `pruning.json` (metrics, Gaussian
reduction, PSNR/ATE differences to the unpruned run, per-phase time breakdown) and
`pruning.png` (per-frame mapping loss and Gaussian count of the three runs, pruning stages
marked). Prints a Markdown table row per run.

`--offline 0.4,0.3` adds a bound on what pruning by removal can keep: the unpruned run's final
map is pruned after the fact to each keep ratio by PWAS and by opacity (`gsc prune`), and each
pruned map and the unpruned one itself are refined alike (`--refine-iters` iterations on every
frame at the run's poses, `gsc merge`'s refinement with nothing merged, its rates decaying to
`--lr-final`) and evaluated. Unlike the online runs, whose later frames regrow different
numbers of Gaussians after each stage, the two scores are compared at exactly the same count,
chosen from a map that saw every frame.

Time: per-phase means over all frames from each frame's `ms` record in `/slam/stats`
(tracking, densification, mapping, pwas, pruning, refinement); "logging" is the run's wall
time per frame minus the mean in-frame total (log writing, frame loading, snapshots). This
2-core machine is shared, so seconds per frame are reported beside their ratio to the
unpruned run of the same call, and process CPU seconds beside wall seconds.

Usage:
    python bench/pruning.py                        # the synthetic room (gsc synth), 60 frames
    python bench/pruning.py /work/shared/data/tsdffusion_tabletop_box
    python bench/pruning.py SEQ --frames 0:120 --set mapping.final_iters=0 --out bench_out/x
    python bench/pruning.py SEQ --runs unpruned,pwas,pwas@0.5,pwas@0.7   # a keep-ratio sweep
    python bench/pruning.py SEQ --runs unpruned --reuse --offline 0.4,0.3 --refine-iters 1000
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.io.mcap_log import TOPIC_STATS, LogReader
from gscompress.pipeline import evaluate_log, merge_logs, prune_log, slam_file
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.refining import DEFAULT_LR_FINAL
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.slam.config import resolve_config, save_config
from gscompress.slam.results import PHASES

RUNS: dict[str, dict[str, Any]] = {
    "unpruned": {"prune.stages": ()},
    "pwas": {"prune.by": "pwas"},
    "opacity": {"prune.by": "opacity"},
}
"""Run name -> config overrides on top of the shared config."""


def run_overrides(name: str) -> dict[str, Any]:
    """Config overrides of a run name: a key of RUNS, or "RUN@KEEP" (e.g. "pwas@0.5") for that
    run at another keep ratio, so one call can trace the Gaussians-against-PSNR trade-off."""
    run, _, keep = name.partition("@")
    if run not in RUNS or (keep and run == "unpruned"):
        raise SystemExit(f"unknown run {name!r}: use {', '.join(RUNS)} or pwas@KEEP / opacity@KEEP")
    return {**RUNS[run], **({"prune.keep": float(keep)} if keep else {})}


METRICS = ("ate_rmse_cm", "psnr", "ssim", "depth_l1_cm", "gaussians", "bytes")


def read_stats(log_path: Path) -> list[dict[str, Any]]:
    """The `/slam/stats` records of a log, in order."""
    with LogReader(log_path) as reader:
        return [json.loads(m.data) for _, _, m in reader.iter_messages([TOPIC_STATS])]


def breakdown(stats: list[dict[str, Any]], wall_s_per_frame: float) -> dict[str, float]:
    """Mean milliseconds per frame of each phase, logging, and PWAS as a share of frame time."""
    n = max(len(stats), 1)
    out = {p: sum(s["ms"].get(p, 0.0) for s in stats) / n for p in PHASES}
    out["in_frame_total"] = sum(s["ms"].get("total", 0.0) for s in stats) / n
    out["logging"] = max(1e3 * wall_s_per_frame - out["in_frame_total"], 0.0)
    out["wall"] = 1e3 * wall_s_per_frame
    out["pwas_percent_of_frame"] = 100.0 * out["pwas"] / out["wall"] if out["wall"] else 0.0
    return {k: round(v, 2) for k, v in out.items()}


def run_one(
    name: str, seq: Path, work: Path, overrides: dict[str, Any], opts: argparse.Namespace
) -> dict[str, Any]:
    """Run SLAM with `overrides`, evaluate the log, and collect its stats."""
    config = resolve_config(opts.preset).with_overrides(**overrides)
    config_path = save_config(config, work / f"{name}.yaml")
    log_path = work / f"{name}.mcap"
    if opts.reuse and log_path.is_file():
        with LogReader(log_path) as reader:
            result = dict(reader.metadata.results)
        cpu_s = None
    else:
        cpu0 = time.process_time()
        result = slam_file(
            seq,
            log_path,
            SlamOptions(config_path=config_path, frames=opts.frames),  # the resolved config
            command=f"bench/pruning.py ({name})",
            force=True,
        )
        cpu_s = time.process_time() - cpu0
    frames = int(result["frames"])
    evaluation = evaluate_log(log_path, seq, ImageOptions(lpips=False, every=opts.eval_every))
    stats = read_stats(log_path)
    wall = float(result["seconds_per_frame"])
    record: dict[str, Any] = {k: evaluation.get(k) for k in METRICS}
    record.update(
        {
            "log": str(log_path),
            "frames": frames,
            "gaussians_max": max(s["gaussians"] for s in stats),
            "seconds_per_frame": wall,
            "device": result.get("device"),
            "render_backend": result.get("render_backend"),
            "cpu_seconds_per_frame": round(cpu_s / frames, 4) if cpu_s is not None else None,
            "ms": breakdown(stats, wall),
            "stage_positions": [
                i for i, s in enumerate(stats) if str(s.get("event", "")).startswith("prune")
            ],
            "loss_mapping": [s.get("loss_mapping") for s in stats],
            "gaussians_per_frame": [s["gaussians"] for s in stats],
            "refinement": [
                {"frame": s["frame"], "iters": s["refine_iters"], "loss": s.get("loss_refine")}
                for s in stats
                if "refine_iters" in s
            ],
        }
    )
    return record


def compare(runs: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Each pruned run against the unpruned one: reduction, PSNR/SSIM deltas, ATE and time."""
    base = runs.get("unpruned")
    if base is None:
        return {}
    out = {}
    for name, run in runs.items():
        if name == "unpruned":
            continue
        ate, ate0 = run["ate_rmse_cm"], base["ate_rmse_cm"]
        kept = run["gaussians"] / base["gaussians"]
        slower = run["seconds_per_frame"] / base["seconds_per_frame"]
        out[name] = {
            "gaussian_reduction_percent": round(100 * (1 - kept), 1),
            "psnr_delta_db": round(run["psnr"] - base["psnr"], 3),
            "ssim_delta": round(run["ssim"] - base["ssim"], 4),
            "ate_ratio": round(ate / ate0, 3) if ate is not None and ate0 else None,
            "seconds_per_frame_ratio": round(slower, 3),
        }
    return out


def plot(runs: dict[str, dict[str, Any]], title: str, path: Path) -> Path:
    """Per-frame mapping loss and Gaussian count of the runs, pruning stages marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    colors = {"unpruned": "black", "pwas": "tab:blue", "opacity": "tab:orange"}
    stages: set[int] = set()
    for name, run in runs.items():
        frames = np.arange(len(run["loss_mapping"]))
        loss = np.array([np.nan if v is None else v for v in run["loss_mapping"]], dtype=float)
        color = colors.get(name)
        top.plot(frames, loss, label=name, color=color, linewidth=1.2)
        bottom.plot(frames, run["gaussians_per_frame"], label=name, color=color, linewidth=1.2)
        stages.update(run["stage_positions"])
    for axis in (top, bottom):
        for position in sorted(stages):
            axis.axvline(position, color="tab:red", linestyle="--", linewidth=0.8)
        axis.grid(alpha=0.3)
    top.set_yscale("log")
    top.set_ylabel("mapping loss (mean per frame)")
    top.set_title(f"{title}: mapping loss around the pruning stages (dashed)")
    top.legend()
    bottom.set_ylabel("Gaussians")
    bottom.set_xlabel("frame (processing position)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def offline_bound(
    unpruned: dict[str, Any], seq: Path, work: Path, keeps: list[float], opts: argparse.Namespace
) -> dict[str, dict[str, Any]]:
    """The unpruned run's final map pruned afterwards to each keep by PWAS and by opacity, each
    and the unpruned map refined alike on every frame, and evaluated (see the module doc)."""
    source = Path(unpruned["log"])
    maps = {"unpruned": source}
    for keep in keeps:
        for by in ("pwas", "opacity"):
            maps[f"{by}@{keep:g}"] = pruned = work / f"offline_{by}@{keep:g}.mcap"
            prune_log(source, pruned, keep, by=by, force=True)
    out: dict[str, dict[str, Any]] = {}
    for name, log_path in maps.items():
        refined = work / f"offline_{name}_refined.mcap"
        merge_logs(
            log_path,
            None,
            refined,
            seq=seq,
            iters=opts.refine_iters,
            lr_final=opts.lr_final,
            force=True,
        )
        evaluation = evaluate_log(refined, seq, ImageOptions(lpips=False, every=opts.eval_every))
        out[name] = {k: evaluation.get(k) for k in ("psnr", "ssim", "gaussians")}
        out[name]["psnr_delta_db"] = round(out[name]["psnr"] - out["unpruned"]["psnr"], 3)
    return out


def table_row(name: str, run: dict[str, Any], seq: str) -> str:
    """One Markdown row: sequence, run, Gaussians, PSNR, SSIM, ATE, s/frame."""
    ate = run["ate_rmse_cm"]
    return (
        f"| {seq} | {name} | {run['gaussians']} | {run['psnr']:.2f} | {run['ssim']:.3f} | "
        f"{'-' if ate is None else f'{ate:.3f}'} | {run['seconds_per_frame']:.2f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seq", nargs="?", default=None, help="sequence folder (default: synth)")
    parser.add_argument("--name", default=None, help="sub-folder of --out (default: seq name)")
    parser.add_argument("--frames", default="all")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--set", action="append", default=[], help="dotted.key=yaml_value")
    parser.add_argument(
        "--runs", default=",".join(RUNS), help=f"of {', '.join(RUNS)}; RUN@KEEP for another keep"
    )
    parser.add_argument("--eval-every", type=int, default=1)
    parser.add_argument("--out", default="bench_out/pruning")
    parser.add_argument("--reuse", action="store_true", help="evaluate existing logs again")
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    parser.add_argument(
        "--offline", default="", help="keep ratios (e.g. 0.4,0.3) of the after-the-fact bound"
    )
    parser.add_argument("--refine-iters", type=int, default=1000, help="for --offline")
    parser.add_argument(
        "--lr-final", type=float, default=DEFAULT_LR_FINAL, help="for --offline, as gsc merge's"
    )
    opts = parser.parse_args()
    if opts.threads:
        torch.set_num_threads(opts.threads)
    logging.basicConfig(level=logging.WARNING)

    out = Path(opts.out)
    if opts.seq is None:
        seq = out / "synthetic_seq"
        if not seq.is_dir() or not any(seq.iterdir()):
            write_synthetic_sequence(seq, frames=60)  # what `gsc synth -o DIR` writes
        name = opts.name or "synthetic"
    else:
        seq = Path(opts.seq)
        name = opts.name or seq.name
    work = out / name
    work.mkdir(parents=True, exist_ok=True)
    shared = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in opts.set)}

    keeps = [float(k) for k in opts.offline.split(",")] if opts.offline else []
    if keeps and "unpruned" not in opts.runs.split(","):  # before hours of runs, not after
        raise SystemExit("--offline prunes the unpruned run's map: include it in --runs")
    runs: dict[str, dict[str, Any]] = {}
    for run_name in opts.runs.split(","):
        overrides = {**shared, **run_overrides(run_name)}
        runs[run_name] = run_one(run_name, seq, work, overrides, opts)
        print(table_row(run_name, runs[run_name], name), flush=True)

    offline: dict[str, dict[str, Any]] = {}
    if keeps:
        offline = offline_bound(runs["unpruned"], seq, work, keeps, opts)
        print(f"| run, refined {opts.refine_iters} iterations | Gaussians | PSNR dB | change |")
        print("|---|---|---|---|")
        for run_name, row in offline.items():
            print(
                f"| {run_name} | {row['gaussians']} | {row['psnr']:.2f} | "
                f"{row['psnr_delta_db']:+.2f} |",
                flush=True,
            )

    report = {
        "sequence": str(seq),
        "frames": opts.frames,
        "preset": opts.preset,
        "overrides": shared,
        "torch_threads": torch.get_num_threads(),
        "config": resolve_config(opts.preset).with_overrides(**shared).to_dict(),
        "runs": runs,
        "versus_unpruned": compare(runs),
        "offline": {"refine_iters": opts.refine_iters, "lr_final": opts.lr_final, "runs": offline}
        if offline
        else None,
        "plot": str(plot(runs, name, work / "pruning.png")),
    }
    (work / "pruning.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    print(json.dumps({"versus_unpruned": report["versus_unpruned"], "json": str(work)}, indent=1))
    for run_name, run in runs.items():
        print(run_name, json.dumps(run["ms"]))


if __name__ == "__main__":
    main()
