"""Benchmark the offline commands on a large log, against a plain copy of the same file.

Builds a log with one N-Gaussian map (default 1,000,000, isotropic, SH degree 0, PWAS scored)
plus 300 poses, then runs `gsc prune --keep 0.3`, `gsc share --budget 0.2`, `gsc export-ply` and
`gsc info` each in a fresh interpreter (as a user would: start-up and imports included), and
copies the log with shutil.copyfile in the same run as the baseline. Prints one JSON object per
measurement and a summary object; peak RSS is each child's own VmHWM.

Usage: python bench/offline.py [--gaussians 1000000] [--repeat 3] [--out results.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gscompress.gaussians import random_map
from gscompress.io.mcap_log import LogMetadata, LogWriter

# Peak RSS from VmHWM: ru_maxrss survives fork+exec on Linux and would report the parent's peak.
CHILD = """
import json, sys, time
t0 = time.perf_counter()
from gscompress_cli.main import cli
try:
    cli(json.loads(sys.argv[1]))
except SystemExit as e:
    assert not e.code, e
hwm = next(line for line in open("/proc/self/status") if line.startswith("VmHWM"))
print(json.dumps({"in_process_s": time.perf_counter() - t0,
                  "peak_rss_mb": int(hwm.split()[1]) / 1024,
                  "torch_imported": "torch" in sys.modules}))
"""


def make_log(path: Path, n: int) -> None:
    with LogWriter(path, LogMetadata(command="bench/offline.py")) as log:
        for i in range(300):
            T = np.eye(4)
            T[0, 3] = i * 0.01
            log.write_pose(T, i * 33_000_000)
        log.write_gaussians(random_map(n, seed=0), 300 * 33_000_000)


def run_child(args: list[str]) -> dict[str, float]:
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(args)], capture_output=True, text=True, check=True
    )
    wall = time.perf_counter() - t0
    result: dict[str, float] = json.loads(out.stdout.strip().splitlines()[-1])
    result["wall_s"] = wall
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None, help="also write the results here")
    opts = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        src = tmp / "big.mcap"
        t0 = time.perf_counter()
        make_log(src, opts.gaussians)
        build_s = time.perf_counter() - t0
        size_mb = src.stat().st_size / 2**20
        commands = {
            "copy": None,
            "prune --keep 0.3": ["prune", str(src), "--keep", "0.3", "-o", str(tmp / "p.mcap")],
            "share --budget 0.2": ["share", str(src), str(tmp / "s.mcap")],
            "export-ply": ["export-ply", str(src), "-o", str(tmp / "e.ply")],
            "info": ["info", str(src)],
        }
        for name, args in commands.items():
            walls, rows = [], []
            for _ in range(opts.repeat):
                for leftover in ("p.mcap", "s.mcap", "e.ply", "copy.mcap"):
                    (tmp / leftover).unlink(missing_ok=True)
                if args is None:
                    t0 = time.perf_counter()
                    shutil.copyfile(src, tmp / "copy.mcap")
                    os.sync()
                    walls.append(time.perf_counter() - t0)
                else:
                    rows.append(run_child(args))
                    walls.append(rows[-1]["wall_s"])
            row = {
                "command": name,
                "gaussians": opts.gaussians,
                "log_mb": round(size_mb, 1),
                "threads": os.cpu_count(),
                "wall_s_median": round(statistics.median(walls), 3),
                "wall_s_all": [round(w, 3) for w in walls],
            }
            if rows:
                row["peak_rss_mb"] = round(max(r["peak_rss_mb"] for r in rows), 1)
                row["torch_imported"] = any(r["torch_imported"] for r in rows)
            results.append(row)
            print(json.dumps(row), flush=True)
    copy_s = results[0]["wall_s_median"]
    summary = {
        "summary": "offline commands vs copy",
        "build_log_s": round(build_s, 2),
        "ratio_to_copy": {r["command"]: round(r["wall_s_median"] / copy_s, 1) for r in results[1:]},
    }
    print(json.dumps(summary))
    if opts.out:
        opts.out.write_text(json.dumps({"rows": results, **summary}, indent=2))


if __name__ == "__main__":
    main()
