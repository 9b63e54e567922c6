"""The five-minute walk: two robots map a room, one sends the other 50 kB of its map.

Runs every step through the `gsc` command line, as a user would, and prints each command:
1. `gsc synth` makes the project's synthetic RGB-D room (40 frames).
2. Record: `gsc slam` maps it twice, as two robots: A on frames 0-23, B on frames 16-39.
3. Look: `gsc render` draws A's map beside the same map coloured by PWAS importance.
4. Prune: `gsc prune --keep 0.3 --map-only` keeps A's 30% most important Gaussians.
5. Share: `gsc share --budget 50kB` cuts the best of A's map that fits in 50 kB.
6. Merge: `gsc merge` puts the share into B's map and refines it on B's frames.
7. Eval: `gsc eval` scores B alone and B with the share on A's frames (poses refined).
8. Export: `gsc export-ply` writes a PLY any splat viewer opens.

Usage: python examples/demo.py [--out demo_out] [--frames 40] [--size 160x120]
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from pathlib import Path


def gsc(*args: object) -> None:
    """Run one gsc command, echoing it; stop the demo with its exit status if it fails (gsc has
    said why, in one line)."""
    words = ["gsc", *map(str, args)]
    print(f"\n$ {shlex.join(words)}", flush=True)
    done = subprocess.run([sys.executable, "-m", "gscompress_cli", *words[1:]], check=False)
    if done.returncode != 0:
        raise SystemExit(done.returncode)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("demo_out"))
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", default="160x120")
    opts = parser.parse_args()
    out: Path = opts.out
    out.mkdir(parents=True, exist_ok=True)  # a rerun replaces the demo's own outputs only
    seq = out / "synthetic"
    n = opts.frames
    frames_a, frames_b = f"0:{(3 * n) // 5}", f"{(2 * n) // 5}:{n}"  # overlapping by a fifth
    a, b = out / "robot_a.mcap", out / "robot_b.mcap"

    gsc("synth", "-o", seq, "--frames", n, "--size", opts.size, "--supersample", 2, "--force")
    gsc("slam", seq, "--frames", frames_a, "-o", a, "--force")
    gsc("slam", seq, "--frames", frames_b, "-o", b, "--force")
    middle = (3 * n) // 10
    gsc(
        "render",
        a,
        "--seq",
        seq,
        "--frames",
        f"{middle}:{middle + 1}",
        "--color",
        "rgb",
        "--color",
        "importance",
        "--side-by-side",
        "-o",
        out / "pictures",
        "--force",
    )
    gsc("prune", a, "--keep", "0.3", "--map-only", "-o", out / "robot_a_pruned.mcap", "--force")
    gsc("share", a, "-o", out / "share.mcap", "--budget", "50kB", "--force")
    gsc("merge", b, out / "share.mcap", "-o", out / "robot_b_merged.mcap", "--seq", seq, "--force")
    for log in (b, out / "robot_b_merged.mcap"):
        gsc(
            "eval",
            log,
            "--seq",
            seq,
            "--frames",
            frames_a,
            "--poses-from",
            a,
            "--refine-poses",
            100,
            "--no-lpips",
        )
    gsc("export-ply", a, "-o", out / "robot_a.ply", "--force")
    print(
        f"\nDone. Open {out}/*.ply in a splat viewer, {out}/*.mcap in Foxglove, and "
        f"{out}/pictures/side_by_side/ for the pictures."
    )


if __name__ == "__main__":
    main()
