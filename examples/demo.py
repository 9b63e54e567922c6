"""The embedded demo: synthetic sequence -> SLAM with PWAS -> eval -> prune -> share -> PLY.

Runs every step through the `gsc` command line, as a user would, and prints each command:
`gsc synth` makes the project's synthetic RGB-D sequence, `gsc slam` maps it (cpu preset) and
scores every Gaussian, `gsc eval` reports its ATE, PSNR, SSIM and LPIPS, then the offline
commands prune the map, cut a 20% share for another agent
and export PLY files for splat viewers.

Usage: python examples/demo.py [--out demo_out] [--frames 40] [--size 160x120]
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from pathlib import Path


def gsc(*args: object) -> None:
    """Run one gsc command, echoing it; stop the demo if it fails."""
    words = ["gsc", *map(str, args)]
    print(f"\n$ {shlex.join(words)}", flush=True)
    subprocess.run([sys.executable, "-m", "gscompress_cli", *words[1:]], check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("demo_out"))
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", default="160x120")
    opts = parser.parse_args()
    out: Path = opts.out
    out.mkdir(parents=True, exist_ok=True)  # a rerun replaces the demo's own outputs only
    seq = out / "synthetic"

    gsc("synth", seq, "--frames", opts.frames, "--size", opts.size, "--supersample", 2, "--force")
    gsc("slam", seq, "-o", out / "map.mcap", "--size", opts.size, "--force")
    gsc("info", out / "map.mcap")
    gsc("eval", out / "map.mcap", "--seq", seq)
    gsc("prune", out / "map.mcap", "--keep", "0.3", "-o", out / "map_pruned.mcap", "--force")
    gsc(
        "share", "--budget", "0.2", out / "map.mcap", out / "share.mcap",
        "--ply", out / "share.ply", "--force",
    )  # fmt: skip
    gsc("export-ply", out / "map.mcap", "-o", out / "map.ply", "--force")
    gsc("info", out / "share.mcap")
    print(f"\nDone. Open {out}/*.ply in a 3DGS viewer and {out}/*.mcap in Foxglove.")


if __name__ == "__main__":
    main()
