"""Benchmark `gsc slam`: ATE, PSNR/SSIM on the training views, seconds per frame, Gaussians.

Runs `gscompress.pipeline.slam_file` on a sequence folder (or on the synthetic room, written
to a temporary folder at the working size as `gsc synth` would), then scores the log as `gsc
eval` does (`gscompress.pipeline.evaluate_log`, without LPIPS: ATE, PSNR/SSIM of the final map
at every `--eval-every`-th estimated pose) and adds the Gaussian counts and mean phase times of
its per-frame stats. Prints one JSON object (and writes it with --json-out).

Wall-clock seconds are what a user waits; process CPU seconds are reported beside them because
this 2-core machine is shared and wall time then includes waiting for the CPU.

Usage:
    python bench/slam.py SEQ [--preset cpu] [--frames all] [--size WxH] [--no-prune]
        [--set mapping.iters=20 ...] [--out run.mcap] [--json-out result.json]
    python bench/slam.py synthetic:60 --size 320x240   # the synthetic room, 60 frames
    python bench/slam.py SEQ --log run.mcap            # only evaluate a log of `gsc slam`
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.io.mcap_log import TOPIC_STATS, LogReader
from gscompress.pipeline import evaluate_log, slam_file
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.slam.config import resolve_config, save_config


def evaluate(log_path: Path, seq: Path, eval_every: int = 1) -> dict[str, Any]:
    """`gsc eval`'s metrics of a SLAM log (no LPIPS), its Gaussian counts and mean phase times."""
    metrics = evaluate_log(log_path, seq, ImageOptions(every=eval_every, lpips=False))
    with LogReader(log_path) as log:
        stats = [json.loads(m.data) for _, _, m in log.iter_messages([TOPIC_STATS])]
    phases = ("tracking", "densification", "mapping", "pwas", "pruning", "total")
    ms = {p: float(np.mean([s["ms"].get(p, 0.0) for s in stats[1:] or stats])) for p in phases}
    keys = ("ate_rmse_cm", "ate_splatam_cm", "psnr", "ssim", "depth_l1_cm", "gaussians", "size")
    return {
        "log": str(log_path),
        "sequence": seq.name,
        "frames": metrics["frames_with_pose"],
        **{k: metrics.get(k) for k in keys},
        "gaussians_max": max(s["gaussians"] for s in stats),
        "eval_views": metrics["frames_evaluated"],
        "first_frame_ms": stats[0]["ms"].get("total"),
        "ms_per_frame_after_first": ms,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seq", help="sequence folder, or synthetic:N (the room, N frames)")
    parser.add_argument("--preset", default=None, help="default: the --config's, else cpu")
    parser.add_argument("--config", default=None)
    parser.add_argument("--frames", default="all")
    parser.add_argument("--size", default=None, help="WxH")
    parser.add_argument("--no-prune", action="store_true")
    parser.add_argument("--keep", type=float, default=None)
    parser.add_argument("--set", action="append", default=[], help="dotted.key=yaml_value")
    parser.add_argument("--eval-every", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", default=None, help="keep the log here")
    parser.add_argument("--log", default=None, help="evaluate this existing log instead of running")
    parser.add_argument("--json-out", default=None)
    opts = parser.parse_args()
    if opts.threads:
        torch.set_num_threads(opts.threads)

    size = None
    if opts.size:
        width, height = opts.size.split("x")
        size = (int(width), int(height))
    config = resolve_config(
        opts.preset, opts.config, size=size, keep=opts.keep, no_prune=opts.no_prune
    )
    overrides = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in opts.set)}
    config = config.with_overrides(**overrides)
    tmp = Path(tempfile.mkdtemp(prefix="bench_slam_"))
    config_path = save_config(config, tmp / "config.yaml")
    out = Path(opts.out) if opts.out else tmp / "run.mcap"

    if opts.seq.startswith("synthetic:"):  # the room as `gsc synth` writes it, at the run's size
        n, size = int(opts.seq.split(":")[1]), config.size or (320, 240)
        seq = write_synthetic_sequence(tmp / "synthetic_seq", frames=n, size=size)
    else:
        seq = Path(opts.seq)

    wall: float | None
    cpu: float | None
    if opts.log:
        out, result, wall, cpu = Path(opts.log), None, None, None
    else:
        cpu0, wall0 = time.process_time(), time.perf_counter()
        result = slam_file(
            seq,
            out,
            SlamOptions(config_path=config_path, frames=opts.frames),  # the resolved config
            command="bench/slam.py",
            force=True,
        )
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    report = evaluate(out, seq, opts.eval_every)
    report.update(
        preset=config.preset,
        stages=list(config.prune.stages),
        overrides=overrides,
        seconds_per_frame_wall=None if wall is None else wall / report["frames"],
        seconds_per_frame_cpu=None if cpu is None else cpu / report["frames"],
        torch_threads=torch.get_num_threads(),
        cpus=os.cpu_count(),
        log_results=result,
    )
    text = json.dumps(report, indent=2)
    print(text)
    if opts.json_out:
        Path(opts.json_out).write_text(text + "\n")


if __name__ == "__main__":
    main()
