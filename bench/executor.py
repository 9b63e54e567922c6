"""Benchmark `gsc experiment`'s executors on one machine: wall time of the same tiny study with
the local executor (one run at a time, and --jobs 2) and with Ray (a Ray instance started by
the command), each a fresh `gsc` process in a new folder, plus the time Ray takes to start and
stop on its own. Checks that all give the same rows (one torch thread per run in each).

Prints one JSON object (and writes it with --json-out).

Usage:
    python bench/executor.py [--frames 4] [--size 32x24] [--json-out bench_out/executor.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from gscompress.datasets.synthetic import write_synthetic_sequence

STUDY = [
    "--preset",
    "tiny",
    "--seeds",
    "1",
    "--sweep",
    "0.2",
    "--strategies",
    "random,pwas",
    "--merge-iters",
    "5",
    "--no-lpips",
    "--every",
    "1",
    "--refine-poses",
    "100",
    "--sweep-seeds",
    "1",
    "--protocol",
    "paper",
    "--json",
]
"""The tests' tiny study (tests/conftest.py TINY_STUDY): 11 runs."""

EXECUTORS = {
    "local, one at a time": ["--threads", "1", "experiment", "{seq}", "-o", "{out}", *STUDY],
    "local, --jobs 2": [
        "--threads",
        "2",
        "experiment",
        "{seq}",
        "-o",
        "{out}",
        *STUDY,
        "--jobs",
        "2",
    ],
    "ray, started here": [
        "experiment",
        "{seq}",
        "-o",
        "{out}",
        *STUDY,
        "--executor",
        "ray",
        "--cpus-per-run",
        "1",
    ],
}


def timed(args: list[str]) -> tuple[float, dict[str, Any]]:
    """Wall seconds of a `gsc` command and its JSON output."""
    start = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-m", "gscompress_cli", *args], capture_output=True, text=True, check=False
    )
    seconds = time.perf_counter() - start
    if run.returncode != 0:
        raise SystemExit(f"gsc {' '.join(args)} failed:\n{run.stderr[-2000:]}")
    return seconds, json.loads(run.stdout)


def ray_start_stop() -> float:
    """Seconds to start a Ray instance on this machine and stop it, in a fresh process."""
    code = (
        "import ray; ray.init(include_dashboard=False, log_to_driver=False, "
        "object_store_memory=200 * 1024**2); ray.shutdown()"
    )
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], capture_output=True, check=True)
    bare = time.perf_counter() - start
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import ray"], capture_output=True, check=True)
    return bare - (time.perf_counter() - start)


def rows(folder: Path) -> list[dict[str, Any]]:
    got = json.loads((folder / "results.json").read_text())
    return [{k: v for k, v in row.items() if k != "seconds_per_frame"} for row in got]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--size", default="32x24")
    parser.add_argument("--json-out", type=Path)
    a = parser.parse_args()
    w, h = (int(v) for v in a.size.split("x"))
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    result: dict[str, Any] = {
        "command": " ".join(["python", *sys.argv]),
        "commit": commit,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}",
        "load_average_before": os.getloadavg()[0],
        "study": f"{a.frames} synthetic frames {a.size}, gsc experiment {' '.join(STUDY)}",
        "seconds": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        seq = write_synthetic_sequence(Path(tmp) / "room", a.frames, (w, h))
        timed(["experiment", str(seq), "-o", f"{tmp}/warm", *STUDY])  # kernels, caches
        reference = None
        for name, template in EXECUTORS.items():
            out = Path(tmp) / name.replace(" ", "_").replace(",", "")
            args = [v.format(seq=seq, out=out) for v in template]
            seconds, got = timed(args)
            result["seconds"][name] = round(seconds, 2)
            result["steps"] = got["steps"]
            reference = reference or rows(out)
            result.setdefault("same_rows", True)
            result["same_rows"] &= rows(out) == reference
        result["ray_start_stop_seconds"] = round(ray_start_stop(), 2)
    s = result["seconds"]
    result["ray_over_local"] = round(s["ray, started here"] / s["local, one at a time"], 3)
    result["ray_over_local_jobs_2"] = round(s["ray, started here"] / s["local, --jobs 2"], 3)
    result["load_average_after"] = os.getloadavg()[0]
    text = json.dumps(result, indent=1)
    print(text)
    if a.json_out:
        a.json_out.parent.mkdir(parents=True, exist_ok=True)
        a.json_out.write_text(text + "\n")


if __name__ == "__main__":
    main()
