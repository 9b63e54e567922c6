"""The embedded demo: synthetic sequence -> map -> PWAS scores -> prune -> share -> PLY.

Runs every step through the `gsc` command line, as a user would, and prints each command.
Until `gsc slam` lands, the map is built by back-projecting every 5th frame of the synthetic
sequence at its ground-truth pose (SplaTAM's initialisation of new Gaussians), then scored with
`gsc score`, the same way a map made by any other 3DGS tool would be.

Usage: python examples/demo.py [--out demo_out] [--frames 40] [--size 160x120]
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from gscompress.datasets import open_sequence
from gscompress.gaussians import GaussianMap
from gscompress.io.ply import write_ply
from gscompress.slam.densify import gaussians_from_rgbd


def gsc(*args: object) -> None:
    """Run one gsc command, echoing it; stop the demo if it fails."""
    words = ["gsc", *map(str, args)]
    print(f"\n$ {shlex.join(words)}", flush=True)
    subprocess.run([sys.executable, "-m", "gscompress_cli", *words[1:]], check=True)


def backproject_keyframes(seq: Path, every: int, stride: int) -> GaussianMap:
    """Isotropic Gaussians from every `every`-th frame's RGB-D pixels (ground-truth poses)."""
    sequence = open_sequence(seq)
    parts: list[GaussianMap] = []
    next_id = 0
    for i in range(0, len(sequence), every):
        frame = sequence.frame(i)
        assert frame.T_world_cam is not None
        part = gaussians_from_rgbd(
            frame.color, frame.depth, sequence.intrinsics, frame.T_world_cam,
            stride=stride, first_id=next_id,
        )  # fmt: skip
        parts.append(part)
        next_id += len(part)
    return GaussianMap.concat(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("demo_out"))
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", default="160x120")
    opts = parser.parse_args()
    out: Path = opts.out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    seq = out / "synthetic"

    gsc("synth", seq, "--frames", opts.frames, "--size", opts.size)
    print("\n# build a map: back-project every 5th frame at its ground-truth pose")
    gaussians = backproject_keyframes(seq, every=5, stride=2)
    write_ply(gaussians, out / "initial.ply", importance=False)
    print(f"wrote {out / 'initial.ply'}: {len(gaussians)} Gaussians")
    gsc("score", out / "initial.ply", "--seq", seq, "-o", out / "map.mcap")
    gsc("prune", out / "map.mcap", "--keep", "0.3", "-o", out / "map_pruned.mcap")
    gsc(
        "share", "--budget", "0.2", out / "map.mcap", out / "share.mcap", "--ply", out / "share.ply"
    )
    gsc("export-ply", out / "map.mcap", "-o", out / "map.ply")
    gsc("info", out / "share.mcap")
    print(f"\nDone. Open {out}/*.ply in a 3DGS viewer and {out}/*.mcap in Foxglove.")


if __name__ == "__main__":
    main()
