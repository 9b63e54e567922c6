"""Benchmark offline pruning with and without refinement, scored off the refinement's views.

For each sequence (default: the synthetic room, made here), one `gsc slam` log (cached under
`--out`/NAME/slam.mcap and reused when present; pass `--log` to score an existing one), then:

- the unpruned map, and the unpruned map refined for `--refine` iterations (`prune --keep 1`;
  `--no-whole` skips that refinement, the longest step, when an earlier run has it);
- for each keep ratio and strategy: `gsc prune --keep K --by S` (with `--fold` and
  `--no-fold`: `--folds`) without and with `--refine N --seq SEQ` (anisotropic, as `gsc prune`
  refines by default; `--isotropic` as `gsc prune --isotropic`), and the file's bytes with and
  without `--map-only`;
- with `--inrun LOG` (a `gsc slam` run of the same sequence with its in-run PWAS pruning, the
  one Table 3 compares): that log's map, scored on the same frames at its own poses, and the
  keep ratio `inrun` prunes to its count.

Every map is rendered at the log's estimated poses of the frames that are NOT keyframes (the
refinement's views are the keyframes, `gscompress.pipeline.logs.KEYFRAME_RULE`) and scored
against the sequence: mean PSNR, SSIM and (with `--lpips`) LPIPS. Writes `prune.json` per
sequence and prints one Markdown table row per map.

Usage:
    python bench/prune.py                                   # the synthetic room, 40 frames
    python bench/prune.py /work/shared/data/tsdffusion_tabletop_box --keep 0.3 --refine 500
    python bench/prune.py SEQ --log demo_out/map.mcap --keep 0.1,0.3,0.5 --by pwas,opacity
    python bench/prune.py SEQ --log unpruned.mcap --inrun pwas.mcap --keep 0.3,inrun --by pwas \
        --refine 1000                                      # against Table 3's in-run pruning
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.io.mcap_log import LogReader, read_map, seconds_to_ns
from gscompress.pipeline import evaluate_log, prune_log, slam_file
from gscompress.pipeline.images import ImageOptions
from gscompress.pipeline.logs import recorded_keyframes
from gscompress.pipeline.refining import LogRefiner, RefineOptions
from gscompress.pipeline.slam_run.options import SlamOptions


def off_keyframes(log: Path, keyframe_ns: set[int], seq: Path, lpips: bool) -> dict[str, Any]:
    """Mean PSNR / SSIM / LPIPS of a log's map over the frames that are not keyframes (of the
    log the map was cut from, `keyframe_ns`), at the log's own poses."""
    result = evaluate_log(log, seq, ImageOptions(lpips=lpips))
    frames = [f for f in result["per_frame"] if seconds_to_ns(f["timestamp"]) not in keyframe_ns]
    scores: dict[str, Any] = {"frames": len(frames), "gaussians": result["gaussians"]}
    for name in ("psnr", "ssim", "lpips"):
        values = [f[name] for f in frames if f.get(name) is not None]
        scores[name] = round(float(np.mean(values)), 4) if values else None
    return scores


def bench_sequence(seq: Path, log: Path, work: Path, opts: argparse.Namespace) -> dict[str, Any]:
    """Every map of one sequence, scored; the rows as a dict."""
    with LogReader(log) as reader:
        keyframe_ns = recorded_keyframes(reader)
    if keyframe_ns is None:
        raise SystemExit(f"{log} records no keyframes (/slam/stats): make it with gsc slam")
    options = RefineOptions(opts.refine, device=opts.device, anisotropic=not opts.isotropic)
    refiner = LogRefiner(log, seq, options)
    rows: list[dict[str, Any]] = []

    def score(name: str, path: Path, seconds: float, **fields: Any) -> None:
        row = {"map": name, **fields, **off_keyframes(path, keyframe_ns, seq, opts.lpips)}
        row["file_bytes"], row["seconds"] = path.stat().st_size, round(seconds, 2)
        rows.append(row)
        logging.getLogger("bench").warning("%s", row)

    score("unpruned", log, 0.0, keep=1.0, by="-", refine=0)
    inrun_ratio = 1.0  # (main() refuses --keep inrun without --inrun)
    if opts.inrun is not None:
        score("in-run PWAS pruning (gsc slam)", opts.inrun, 0.0, keep="-", by="pwas", refine=0)
        inrun_ratio = len(read_map(opts.inrun)) / len(read_map(log))
    keeps = [inrun_ratio if k == "inrun" else float(k) for k in opts.keep]
    maps = ([(1.0, "pwas", False)] if opts.whole else []) + [
        (k, s, f == "fold") for k in keeps for s in opts.by for f in opts.folds
    ]
    for keep, by, fold in maps:
        for refine in [opts.refine] if keep == 1.0 else [0, opts.refine]:
            tag = f"{by}_{keep:g}_{'fold' if fold else 'nofold'}"
            out = work / f"prune_{tag}_r{refine}.mcap"
            start = time.perf_counter()
            prune_log(
                log, out, keep, by=by, refine=refiner if refine else None, fold=fold, force=True
            )
            seconds = time.perf_counter() - start
            fields: dict[str, Any] = {"keep": keep, "by": by, "fold": fold, "refine": refine}
            if not refine:
                alone = work / f"prune_{tag}_maponly.mcap"
                prune_log(log, alone, keep, by=by, map_only=True, fold=fold, force=True)
                fields["map_only_bytes"] = alone.stat().st_size
            name = f"prune {keep:.4g} {by}" + (" folded" if fold and keep < 1 else "")
            score(name + (f" +refine {refine}" if refine else ""), out, seconds, **fields)
    return {
        "sequence": str(seq),
        "log": str(log),
        "keyframes": len(keyframe_ns),
        "refine_iters": opts.refine,
        "rows": rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seqs", nargs="*", type=Path, help="sequences (default: synthetic)")
    parser.add_argument("--log", type=Path, default=None, help="an existing log (one sequence)")
    parser.add_argument("--out", type=Path, default=Path("bench_out/prune"))
    parser.add_argument("--keep", default="0.1,0.3,0.5", help="ratios; inrun: --inrun's count")
    parser.add_argument("--folds", default="fold,no-fold", help="fold, no-fold or both")
    parser.add_argument("--inrun", type=Path, default=None, help="in-run pruned log to compare")
    parser.add_argument("--by", default="pwas,opacity")
    parser.add_argument("--refine", type=int, default=200)
    parser.add_argument("--isotropic", action="store_true", help="refine one scale a Gaussian")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--frames", default=None, help="frame subset of the SLAM run")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--lpips", action="store_true")
    parser.add_argument(
        "--no-whole",
        dest="whole",
        action="store_false",
        help="skip refining the whole map (an earlier run at the same N has it)",
    )
    opts = parser.parse_args()
    opts.keep = opts.keep.split(",")
    opts.folds = opts.folds.split(",")
    if "inrun" in opts.keep and opts.inrun is None:
        raise SystemExit("--keep inrun needs --inrun LOG")
    opts.by = opts.by.split(",")
    logging.basicConfig(format="%(message)s")
    seqs = opts.seqs or [opts.out / "synthetic" / "room"]
    if not opts.seqs and not seqs[0].exists():
        write_synthetic_sequence(seqs[0], 40, (160, 120), supersample=2)
    if opts.log is not None and len(seqs) != 1:
        raise SystemExit("--log scores one sequence")
    results = []
    for seq in seqs:
        work = opts.out / seq.name
        work.mkdir(parents=True, exist_ok=True)
        log = opts.log or work / "slam.mcap"
        if not log.exists():
            slam_file(seq, log, SlamOptions(preset=opts.preset, frames=opts.frames))
        result = bench_sequence(seq, log, work, opts)
        (work / "prune.json").write_text(json.dumps(result, indent=2) + "\n")
        results.append(result)
    print("| sequence | map | Gaussians | PSNR | SSIM | LPIPS | file B | map-only B |")
    print("|---|---|---|---|---|---|---|---|")
    for result in results:
        for r in result["rows"]:
            print(
                f"| {Path(result['sequence']).name} | {r['map']} | {r['gaussians']} | "
                f"{r['psnr']} | {r['ssim']} | {r['lpips']} | {r['file_bytes']} | "
                f"{r.get('map_only_bytes', '')} |"
            )


if __name__ == "__main__":
    main()
