"""Frames per second of reading a long ROS 1 recording frame by frame: the reader's fetch by
place in the connection's index against rosbags' fetch by time (a walk of the index from its
start for every frame: how the reader read frame i before), in one process on one open
recording, alternating the two `--repeats` times.

A recording of the synthetic room at `--size` (small by default, so that finding a message,
not decoding it, is what is measured) is written as a ROS 1 bag (`gsc convert`'s writer), then
read whole with each fetch. Prints frames per second of each and their ratio; writes
`ros1_access.json` into `--out`.

Usage:
    python bench/ros1_access.py                       # 1,000 frames of 32x24
    python bench/ros1_access.py --frames 300 --repeats 3 --out /tmp/bench_ros1
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from gscompress.datasets import open_sequence
from gscompress.datasets.base import parse_size
from gscompress.datasets.recording import RecordingSequence
from gscompress.datasets.recording_writer import write_recording
from gscompress.datasets.synthetic import synthetic_sequence
from gscompress.errors import DatasetError


def fetch_by_time(container: Any, locator: Any) -> Any:
    """The message at `locator` found as the reader found it before: rosbags' messages of the
    topic in the one-nanosecond window of its log time (its ROS 1 reader walks the index from
    its start to get there)."""
    topic, log_time, nth, _position = locator
    found = container._reader.messages(
        connections=[container._connections[topic]], start=log_time, stop=log_time + 1
    )
    for k, (_connection, _time, raw) in enumerate(found):
        if k == nth:
            return container._decode(topic, log_time, raw)
    raise DatasetError(f"a {topic} message at {log_time} ns is gone")


def read_all(sequence: RecordingSequence) -> float:
    """Seconds to decode every frame of `sequence`, in order."""
    start = time.perf_counter()
    for i in range(len(sequence)):
        sequence.frame(i)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--size", default="32x24")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("bench_ros1_access"))
    opts = parser.parse_args()
    opts.out.mkdir(parents=True, exist_ok=True)
    bag = opts.out / f"room_{opts.frames}.bag"
    if not bag.exists():
        size = parse_size(opts.size) or (32, 24)
        write_recording(synthetic_sequence(opts.frames, size), bag, "ros1")
    sequence = open_sequence(bag)
    assert isinstance(sequence, RecordingSequence)
    container = sequence._container
    by_place = container.fetch
    seconds: dict[str, list[float]] = {"by place": [], "by time (before)": []}
    for _ in range(opts.repeats):  # interleaved, so that the machine's load falls on both alike
        container.fetch = by_place  # type: ignore[method-assign]
        seconds["by place"].append(read_all(sequence))
        container.fetch = lambda locator: fetch_by_time(container, locator)  # type: ignore[method-assign]
        seconds["by time (before)"].append(read_all(sequence))
    container.fetch = by_place  # type: ignore[method-assign]
    fps = {name: len(sequence) / min(values) for name, values in seconds.items()}
    result = {
        "recording": str(bag),
        "frames": len(sequence),
        "size": opts.size,
        "repeats": opts.repeats,
        "frames_per_second": {name: round(value, 1) for name, value in fps.items()},
        "ratio": round(fps["by place"] / fps["by time (before)"], 2),
    }
    (opts.out / "ros1_access.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
