"""Benchmark `gsc share --solve` against the fixed choices at the same byte budgets.

For one SLAM log and its sequence, and each budget (fractions of the map's fp32 bytes by
default: 2%bytes, 5%bytes, 20%bytes), writes three shares of the map with the same strategy:

- `gsc share LOG --budget B --solve --seq SEQ` (the solver picks codec and sums),
- `gsc share LOG --budget B --codec compact` (compact with the sums, folded: the default),
- `gsc share LOG --budget B --codec compact --no-fold` (compact top-K),
- `gsc share LOG --budget B --codec fp32 --no-fold` (fp32 top-K),

and scores each alone at the sender's estimated poses on the frames that are NOT the log's
keyframes (`gsc eval SHARE --seq SEQ --poses-from LOG`, its `per_frame` entries filtered against
the keyframes `/slam/stats` records): the solver ranks its candidates at a few keyframes, so
these frames are ones it did not choose by. Writes `solve.json` and prints one Markdown row
per share.

Usage:
    python bench/solve.py LOG SEQ [--out bench_out/solve/NAME] [--budgets 2%bytes,5%bytes]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from gscompress.io.mcap_log import LogReader, seconds_to_ns
from gscompress.pipeline.logs import recorded_keyframes

CHOICES = {
    "solve": ["--solve"],
    "compact folded": ["--codec", "compact"],
    "compact top-K": ["--codec", "compact", "--no-fold"],
    "fp32 top-K": ["--codec", "fp32", "--no-fold"],
}


def gsc(*args: str) -> dict[str, Any]:
    """Run `gsc ... --json` (this interpreter's) and return its JSON object."""
    cmd = [sys.executable, "-m", "gscompress_cli", "--threads", "2", *args, "--json"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed: {done.stderr.strip().splitlines()[-1:]}")
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def off_keyframe_psnr(result: dict[str, Any], keyframe_ns: set[int]) -> tuple[int, float]:
    """(frames, mean PSNR) over an eval result's frames that are not keyframes."""
    psnr = [
        f["psnr"] for f in result["per_frame"] if seconds_to_ns(f["timestamp"]) not in keyframe_ns
    ]
    return len(psnr), round(float(np.mean(psnr)), 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("seq", type=Path)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--budgets", default="2%bytes,5%bytes,20%bytes")
    parser.add_argument("--by", default="pwas")
    opts = parser.parse_args()
    out = opts.out or Path("bench_out/solve") / opts.seq.name
    out.mkdir(parents=True, exist_ok=True)
    with LogReader(opts.log) as reader:
        keyframe_ns = recorded_keyframes(reader)
    if keyframe_ns is None:
        raise SystemExit(f"{opts.log} records no keyframes (/slam/stats): make it with gsc slam")
    rows: list[dict[str, Any]] = []
    print("| budget | share | codec (sums, folded) | Gaussians | file bytes | PSNR off keyframes |")
    print("|---|---|---|---|---|---|")
    for budget in opts.budgets.split(","):
        for name, flags in CHOICES.items():
            path = out / f"{name.replace(' ', '_')}_{budget.replace('%', 'pct')}.mcap"
            extra = ["--seq", str(opts.seq)] if name == "solve" else []
            shared = gsc(
                "share",
                str(opts.log),
                str(path),
                "--budget",
                budget,
                "--by",
                opts.by,
                *flags,
                *extra,
                "--force",
            )
            scored = gsc(
                "eval",
                str(path),
                "--seq",
                str(opts.seq),
                "--poses-from",
                str(opts.log),
                "--no-lpips",
            )
            frames, psnr = off_keyframe_psnr(scored, keyframe_ns)
            row = {
                "budget": budget,
                "share": name,
                "codec": shared.get("codec"),
                "sums": shared.get("sums"),
                "fold": shared.get("fold"),
                "gaussians": shared.get("selected"),
                "file_bytes": path.stat().st_size,
                "frames": frames,
                "psnr": psnr,
                "predicted_psnr": shared.get("predicted_psnr"),
            }
            rows.append(row)
            how = f"{row['codec']} ({'sums' if row['sums'] else 'no sums'}, " + (
                "folded)" if row["fold"] else "top-K)"
            )
            print(
                f"| {budget} | {name} | {how} | {row['gaussians']} | "
                f"{row['file_bytes']:,} | {psnr:.2f} |",
                flush=True,
            )
    (out / "solve.json").write_text(json.dumps({"log": str(opts.log), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
