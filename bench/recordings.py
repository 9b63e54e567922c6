"""Benchmark the recording reader against the folder reader on the same frames.

A TUM folder of the synthetic room at 640x480 (made here, or `--seq`) is written as a ROS 2 bag
(MCAP and sqlite storage), a ROS 1 bag and a Foxglove MCAP (`gsc convert`, raw rgb8 and 32FC1);
then each is read whole, in one process, alternating the readers `--repeats` times: opening
(the recording's one pass over its stamps and the pairing) plus `frame(i)` of every frame
(colour and depth decoded). Prints frames per second of each reader and its ratio to the
folder reader's (the folder decodes PNGs; a recording's raw images need no inflate). Writes
`recordings.json` into `--out`.

Usage:
    python bench/recordings.py                     # 30 frames of 640x480
    python bench/recordings.py --frames 60 --repeats 5 --out /tmp/bench_rec
    python bench/recordings.py --seq /work/shared/data/tsdffusion_tabletop_box --frames 100
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from gscompress.datasets import open_sequence
from gscompress.datasets.recording_writer import RECORDING_FORMATS
from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.pipeline.recordings import convert_sequence

NAMES = {"ros2": "bag2", "ros2-sqlite": "bag2s", "ros1": "bag1.bag", "foxglove": "fox.mcap"}


def read_all(path: Path, frames: str) -> tuple[int, float]:
    """(frames, seconds) to open `path` and decode every selected frame."""
    start = time.perf_counter()
    sequence = open_sequence(path, frames=frames)
    for i in range(len(sequence)):
        sequence.frame(i)
    return len(sequence), time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seq", type=Path, default=None, help="a TUM folder [synthetic room]")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("bench_recordings"))
    opts = parser.parse_args()
    opts.out.mkdir(parents=True, exist_ok=True)
    seq = opts.seq
    if seq is None:
        seq = opts.out / "room640"
        if not seq.exists():
            write_synthetic_sequence(seq, opts.frames, (640, 480))
    subset = f"0:{opts.frames}"
    paths = {"folder": seq}
    for fmt in RECORDING_FORMATS:
        out = opts.out / f"{seq.name}_{NAMES[fmt]}"
        if not out.exists():
            convert_sequence(seq, out, fmt, frames=subset)
        paths[fmt] = out
    seconds: dict[str, list[float]] = {name: [] for name in paths}
    counts: dict[str, int] = {}
    for _ in range(opts.repeats):  # interleaved, so that the machine's load falls on all alike
        for name, path in paths.items():
            counts[name], took = read_all(path, subset)
            seconds[name].append(took)
    best = {name: min(values) for name, values in seconds.items()}
    fps = {name: counts[name] / best[name] for name in paths}
    k = open_sequence(seq, frames=subset).intrinsics
    result: dict[str, Any] = {
        "sequence": str(seq),
        "size": [k.width, k.height],
        "frames": counts["folder"],
        "repeats": opts.repeats,
        "frames_per_second": {n: round(v, 2) for n, v in fps.items()},
        "ratio_to_folder": {n: round(v / fps["folder"], 3) for n, v in fps.items()},
        "bytes": {n: _bytes(p) for n, p in paths.items()},
    }
    (opts.out / "recordings.json").write_text(json.dumps(result, indent=2) + "\n")
    print(
        f"| reader | frames/s | x folder | bytes |  ({k.width}x{k.height}, {counts['folder']} "
        f"frames, best of {opts.repeats})"
    )
    print("|---|---|---|---|")
    for name in paths:
        print(
            f"| {name} | {fps[name]:.1f} | {fps[name] / fps['folder']:.2f} | "
            f"{result['bytes'][name]:,} |"
        )


def _bytes(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


if __name__ == "__main__":
    main()
