"""Benchmark `gsc slam`: ATE, PSNR/SSIM on the training views, seconds per frame, Gaussians.

Runs `gscompress.pipeline.slam_file` on a sequence folder (or the in-memory synthetic room),
then reads the log back as a user would: the estimated and ground-truth poses, the per-frame
stats (time breakdown) and the final map, which is rendered at every `--eval-every`-th
estimated pose and compared with the observed frame (PSNR and SSIM on valid-depth pixels,
`gscompress.metrics`). Prints one JSON object (and writes it with --json-out).

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

from gscompress.camera import invert_transform, make_transform, quat_to_rotmat
from gscompress.datasets import open_sequence
from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.io.mcap_log import TOPIC_POSE, TOPIC_STATS, LogReader
from gscompress.metrics import ate_rmse_cm, ate_splatam_cm, psnr, ssim
from gscompress.pipeline import slam_file
from gscompress.render import render
from gscompress.slam.config import resolve_config, save_config
from gscompress.slam.params import GaussianParams


def read_poses(log: LogReader, topic: str) -> np.ndarray:
    """[M, 4, 4] camera-to-world poses of a PoseInFrame topic."""
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    out = []
    for _, _, message in log.iter_messages([topic]):
        p = PoseInFrame.FromString(message.data).pose
        q = np.array([p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z])
        out.append(make_transform(quat_to_rotmat(q), [p.position.x, p.position.y, p.position.z]))
    return np.array(out)


def evaluate(log_path: Path, sequence: Any, eval_every: int = 1) -> dict[str, Any]:
    """ATE, training-view PSNR/SSIM, Gaussian counts and mean phase times of a SLAM log."""
    with LogReader(log_path) as log:
        est = read_poses(log, TOPIC_POSE)
        stats = [json.loads(m.data) for _, _, m in log.iter_messages([TOPIC_STATS])]
        final = log.read_map()
    _, gt = sequence.ground_truth() if sequence.has_ground_truth else (None, None)
    params = GaussianParams.from_map(final).render_inputs()
    psnrs, ssims = [], []
    with torch.no_grad():
        for i in range(0, len(est), eval_every):
            frame = sequence.frame(i)
            T = torch.as_tensor(invert_transform(est[i]), dtype=torch.float32)
            image = render(*(p.detach() for p in params), sequence.intrinsics, T).color
            image = image.clamp(0, 1).numpy()
            valid = frame.depth > 0
            psnrs.append(psnr(image, frame.color, valid))
            ssims.append(ssim(image, frame.color, valid))
    phases = ("tracking", "densification", "mapping", "pwas", "pruning", "total")
    ms = {p: float(np.mean([s["ms"].get(p, 0.0) for s in stats[1:] or stats])) for p in phases}
    return {
        "log": str(log_path),
        "sequence": getattr(sequence, "name", ""),
        "size": [sequence.intrinsics.width, sequence.intrinsics.height],
        "frames": len(est),
        "gaussians": len(final),
        "gaussians_max": max(s["gaussians"] for s in stats),
        "ate_rmse_cm": ate_rmse_cm(gt[: len(est)], est) if gt is not None else None,
        "ate_splatam_cm": ate_splatam_cm(gt[: len(est)], est) if gt is not None else None,
        "psnr_db": float(np.mean(psnrs)),
        "ssim": float(np.mean(ssims)),
        "eval_views": len(psnrs),
        "first_frame_ms": stats[0]["ms"].get("total"),
        "ms_per_frame_after_first": ms,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seq", help="sequence folder, or synthetic:N for the in-memory room")
    parser.add_argument("--preset", default="cpu")
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

    size = tuple(int(v) for v in opts.size.split("x")) if opts.size else None
    config = resolve_config(
        opts.preset, opts.config, size=size, keep=opts.keep, no_prune=opts.no_prune
    )
    overrides = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in opts.set)}
    config = config.with_overrides(**overrides)
    tmp = Path(tempfile.mkdtemp(prefix="bench_slam_"))
    config_path = save_config(config, tmp / "config.yaml")
    out = Path(opts.out) if opts.out else tmp / "run.mcap"

    if opts.seq.startswith("synthetic:"):
        n = int(opts.seq.split(":")[1])
        # the synthetic room is rendered at the working size directly
        sequence: Any = synthetic_sequence(n, config.size or (320, 240))
        seq_arg = None
    else:
        sequence = open_sequence(opts.seq, size=config.size, frames=opts.frames)
        seq_arg = opts.seq

    wall: float | None
    cpu: float | None
    if opts.log:
        out, result, wall, cpu = Path(opts.log), None, None, None
    else:
        cpu0, wall0 = time.process_time(), time.perf_counter()
        result = slam_file(
            seq_arg, out, preset=opts.preset, config_path=config_path, frames=opts.frames,
            command="bench/slam.py", force=True, sequence=sequence,
        )  # fmt: skip
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    report = evaluate(out, sequence, opts.eval_every)
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
