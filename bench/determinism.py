"""Do repeated `gsc slam` runs of one sequence, each in a fresh process, end with the same map?

Runs `gsc --threads T slam SEQ --frames F` `--runs` times, each in its own process (start-up
effects are what this looks for), hashes every final map's parameters and prints one JSON
object: the distinct hashes with how many runs ended on each. One hash means the runs were
reproducible bit for bit. Different thread counts may legitimately end differently (torch's
reductions split by thread); one thread count must not.

Usage:
    python bench/determinism.py SEQ [--runs 6] [--threads 2] [--frames 0:10] [--preset cpu]
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from gscompress.io.mcap_log import LogReader


def map_hash(log: Path) -> str:
    """sha1 (12 hex digits) of the final map's parameter arrays."""
    with LogReader(log) as reader:
        gaussians = reader.read_map()
    digest = hashlib.sha1()
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "ids"):
        digest.update(getattr(gaussians, name).tobytes())
    return digest.hexdigest()[:12]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seq")
    parser.add_argument("--runs", type=int, default=6)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--frames", default="0:10")
    parser.add_argument("--preset", default="cpu")
    opts = parser.parse_args()
    counts: collections.Counter[str] = collections.Counter()
    with tempfile.TemporaryDirectory(prefix="bench_det_") as tmp:
        for k in range(opts.runs):
            log = Path(tmp) / f"run{k}.mcap"
            command = [
                sys.executable,
                "-m",
                "gscompress_cli",
                "--quiet",
                "--threads",
                str(opts.threads),
                "slam",
                opts.seq,
                "-o",
                str(log),
                "--frames",
                opts.frames,
                "--preset",
                opts.preset,
            ]
            run = subprocess.run(command, capture_output=True, text=True)
            if run.returncode != 0:
                sys.exit(f"run {k} failed: {run.stderr.strip().splitlines()[-1:]}")
            counts[map_hash(log)] += 1
    report = {
        "seq": opts.seq,
        "frames": opts.frames,
        "threads": opts.threads,
        "runs": opts.runs,
        "preset": opts.preset,
        "distinct_maps": len(counts),
        "maps": dict(counts),
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
