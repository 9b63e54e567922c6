"""A `gsc slam` run's memory as it goes (docs/recordings.md, "Streaming and memory").

Runs `slam_file` on a sequence at a working size, one thread, and prints the process's RSS (its
anonymous part beside it) above the RSS after the imports: at every 100th frame, at every 200th
step of the final refinement and scoring, and at the end with the peak. `--census` adds, at the
end of the frames and of the final refinement, the torch tensors alive (count and bytes) and
how many of the run's views hold images. `--trim` hands the allocator's free memory back at the
end (glibc's `malloc_trim`): what that returns was free memory the heap kept, not live objects.

    python bench/slam_memory.py SEQ [--frames 0:1000] [--size 64x48] [--config FILE] [--census]
        [--trim]
"""

from __future__ import annotations

import argparse
import gc
import resource
import tempfile
import warnings
from pathlib import Path
from typing import Any

import torch

from gscompress.pipeline import slam_file
from gscompress.pipeline.slam_run import release_free_heap
from gscompress.pipeline.slam_run.options import SlamOptions


def rss_mib() -> tuple[int, int]:
    """The process's resident and anonymous resident memory, MiB."""
    fields = {}
    with open("/proc/self/status") as status:
        for line in status:
            name, _, value = line.partition(":")
            if name in ("VmRSS", "RssAnon"):
                fields[name] = int(value.split()[0]) // 1024
    return fields["VmRSS"], fields["RssAnon"]


def census() -> str:
    """The live torch tensors (count, MiB of their storages) and the views holding images."""
    from gscompress.slam.system import SlamSystem  # (imported by the run: not in the base)

    gc.collect()
    with warnings.catch_warnings():  # (isinstance on torch's deprecated aliases warns)
        warnings.simplefilter("ignore", FutureWarning)
        live = gc.get_objects()
        tensors = [t for t in live if isinstance(t, torch.Tensor)]
        systems = [s for s in live if isinstance(s, SlamSystem)]
    storages = {t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in tensors}
    views = [v for s in systems for v in {id(v): v for v in [*s.views, *s.keyframes]}.values()]
    holding = sum(1 for v in views if v.color.numel())
    return (
        f"census: {len(tensors)} tensors, {sum(storages.values()) / 2**20:.2f} MiB; "
        f"{holding} of {len(views)} views hold images"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("seq")
    parser.add_argument("--frames", default="all")
    parser.add_argument("--size", default="64x48", help="working size WxH")
    parser.add_argument("--config", default=None, help="a gsc slam config (e.g. a size cap)")
    parser.add_argument("--census", action="store_true")
    parser.add_argument("--trim", action="store_true")
    args = parser.parse_args()
    width, height = (int(x) for x in args.size.split("x"))
    torch.set_num_threads(1)
    base = rss_mib()

    def report(where: str) -> None:
        rss, anon = rss_mib()
        print(f"{where}: RSS +{rss - base[0]} MiB (anonymous +{anon - base[1]})", flush=True)

    def progress(done: int, total: int, stats: dict[str, Any]) -> None:
        if done % 100 == 0 or done == total:
            report(f"frame {done}, {stats.get('gaussians')} Gaussians")
            if args.census and done == total:
                print(census(), flush=True)

    def phases(name: str, done: int, total: int | None) -> None:
        if total and (done % 200 == 0 or done == total):
            report(f"{name} {done}/{total}")
            if args.census and done == total and name.startswith("final refinement"):
                print(census(), flush=True)

    print(f"RSS after the imports: {base[0]} MiB", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        options = SlamOptions(frames=args.frames, size=(width, height), config_path=args.config)
        slam_file(args.seq, Path(tmp) / "run.mcap", options, progress=progress, phases=phases)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024
    report("end")
    print(f"peak: +{peak - base[0]} MiB above the imports", flush=True)
    if args.trim:
        release_free_heap()
        report("after malloc_trim")


if __name__ == "__main__":
    main()
