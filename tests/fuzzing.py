"""Structural fuzzing of the readers of untrusted files, and its long-run driver (`make fuzz`).

Each reader is a `FuzzTarget`: a name, a function that makes a valid input (bytes) from a few
choices, a function that mutates such an input structurally, and the read that a command does
with a file. A case passes when the read succeeds or raises a `GscError` in one line; anything
else (another exception, a numpy warning, a case over `HANG_SECONDS`) is a defect, and so, in
the long run, is a case whose read takes more memory than the policy allows: peak RSS minus the
RSS after imports, in the same process, at most max(300 MB, 20 x the input's bytes)
(`bounded.memory_bound`), whatever the read ends with. Add a reader by appending a target to
`TARGETS`; the targets live in fuzz_mcap.py, fuzz_maps.py, fuzz_sequences.py,
fuzz_recordings.py and fuzz_view.py (the viewer's page messages), their edits in
fuzz_mutations.py.

Choices come from a `Chooser`: hypothesis' data in tests/test_fuzz.py, a seeded random generator
here, so that the same mutators serve the fast part of the test suite and the long run.

    python tests/fuzzing.py --cases 10000           # every target, each in its own process
    python tests/fuzzing.py --target ply --cases 500
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bounded import memory_bound, peak_rss_bytes, reset_peak_rss, rss_bytes
from fuzz_maps import (
    mutate_compact,
    mutate_ply,
    mutate_sog,
    mutate_spz,
    read_compact,
    read_ply_map,
    read_sog_map,
    read_spz_map,
    valid_compact,
    valid_ply,
    valid_sog,
    valid_spz,
)
from fuzz_mcap import mutate_log, read_log, valid_log
from fuzz_mutations import Chooser, RandomChooser
from fuzz_recordings import mutate_recording, read_recording, valid_recording
from fuzz_sequences import mutate_sequence, read_sequence, valid_sequence
from fuzz_view import mutate_messages, read_view, valid_messages

from gscompress.errors import GscError

__all__ = ["TARGETS", "FuzzTarget", "RandomChooser", "run_case"]

HANG_SECONDS = 10.0
"""A case running longer than this is counted as a hang (and stopped, in the long run)."""


@dataclass(frozen=True)
class FuzzTarget:
    """One reader under fuzzing.

    Attributes:
        name: what `--target` calls it.
        suffix: the file-name suffix of its inputs.
        make_valid_input: a valid input from a few choices.
        mutate: a structurally edited input from a valid one.
        read: what a command does with such a file; returns normally or raises GscError.
        requires: a module the read needs that an install may lack (an optional extra): the
            target is skipped without it.
    """

    name: str
    suffix: str
    make_valid_input: Callable[[Chooser], bytes]
    mutate: Callable[[bytes, Chooser], bytes]
    read: Callable[[Path], None]
    requires: str | None = None

    def missing(self) -> str | None:
        """Why this target cannot run here (its `requires` is not installed), or None."""
        if self.requires is None or importlib.util.find_spec(self.requires) is not None:
            return None
        return f"{self.requires} is not installed (the optional [view] extra)"


TARGETS: list[FuzzTarget] = [
    FuzzTarget("mcap", ".mcap", valid_log, mutate_log, read_log),
    FuzzTarget("ply", ".ply", valid_ply, mutate_ply, read_ply_map),
    FuzzTarget("compact", ".bin", valid_compact, mutate_compact, read_compact),
    FuzzTarget("spz", ".spz", valid_spz, mutate_spz, read_spz_map),
    FuzzTarget("sog", ".sog", valid_sog, mutate_sog, read_sog_map),
    FuzzTarget("sequence", ".zip", valid_sequence, mutate_sequence, read_sequence),
    FuzzTarget("recordings", ".zip", valid_recording, mutate_recording, read_recording),
    FuzzTarget("view", ".msgpack", valid_messages, mutate_messages, read_view, requires="viser"),
]


class Hang(Exception):
    """A case ran past `HANG_SECONDS`."""


def run_case(target: FuzzTarget, c: Chooser, folder: Path) -> tuple[str, str]:
    """Make, mutate and read one input. Returns (outcome, detail): "ok", "refused" (a
    GscError), or "defect" with the traceback (any other exception or a warning)."""
    path = make_case(target, c, folder)
    return read_case(target, path)


def make_case(target: FuzzTarget, c: Chooser, folder: Path) -> Path:
    """A mutated input of `target`, written in `folder`."""
    path = folder / f"case{target.suffix}"
    path.write_bytes(target.mutate(target.make_valid_input(c), c))
    return path


def read_case(target: FuzzTarget, path: Path) -> tuple[str, str]:
    """Read one input: see `run_case`."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # numpy's RuntimeWarnings are defects too
            target.read(path)
    except GscError as exc:
        if "\n" in str(exc):
            return "defect", f"a GscError of several lines: {exc!r}"
        return "refused", str(exc)
    except Hang:
        raise
    except Exception:  # the defects the fuzzing looks for, recorded rather than raised
        return "defect", traceback.format_exc()
    return "ok", ""


def _on_alarm(_signum: int, _frame: Any) -> None:
    raise Hang


def _warmed_up(target: FuzzTarget, folder: Path) -> None:
    """Read a few valid inputs, so that what a read imports on first use is imported before the
    base RSS is measured."""
    for seed in range(3):
        path = folder / f"valid{target.suffix}"
        path.write_bytes(target.make_valid_input(RandomChooser(seed)))
        read_case(target, path)


def fuzz(target: FuzzTarget, cases: int, seed: int) -> dict[str, Any]:
    """Run `cases` cases of `target`; counts, the slowest case, the largest peak RSS of a read
    above the RSS after imports, and defects (a read whose peak is past its input's
    `memory_bound` is one, whatever it ended with). Each read's peak is its own: the high-water
    mark is reset before it (`reset_peak_rss`)."""
    counts = {"ok": 0, "refused": 0, "defect": 0, "hang": 0, "over memory": 0}
    defects: list[str] = []
    slowest = (0.0, -1)
    largest = peak = 0
    signal.signal(signal.SIGALRM, _on_alarm)
    with tempfile.TemporaryDirectory() as tmp:
        _warmed_up(target, Path(tmp))
        base = rss_bytes()
        start = time.perf_counter()
        for case in range(cases):
            path = make_case(target, RandomChooser(seed * 1_000_003 + case), Path(tmp))
            size = path.stat().st_size
            largest = max(largest, size)
            reset_peak_rss()  # (what making the case took is not the read's)
            began = time.perf_counter()
            signal.setitimer(signal.ITIMER_REAL, HANG_SECONDS)
            try:
                outcome, detail = read_case(target, path)
            except Hang:
                outcome, detail = "hang", f"case {case} ran over {HANG_SECONDS} s"
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            took = time.perf_counter() - began
            slowest = max(slowest, (took, case))
            above = peak_rss_bytes() - base
            peak = max(peak, above)
            if above > memory_bound(size):
                outcome = "over memory"
                detail = f"peak RSS {above} bytes above base, over {memory_bound(size)} ({detail})"
            counts[outcome] += 1
            if outcome in ("defect", "hang", "over memory") and len(defects) < 20:
                defects.append(f"case {case} (seed {seed}):\n{detail}")
        seconds = time.perf_counter() - start
    return {
        "target": target.name,
        "cases": cases,
        **counts,
        "cases_per_second": round(cases / seconds, 1),
        "slowest_case_seconds": round(slowest[0], 3),
        "slowest_case": slowest[1],
        "peak_rss_above_base_mib": round(max(peak, 0) / 2**20, 1),
        "largest_input_bytes": largest,
        "defects": defects,
    }


def main(argv: Sequence[str] | None = None) -> int:
    """The long run: each target in its own process, all at once (so that each peak RSS is its
    own); their reports are printed in target order."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=10_000, help="cases per target")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--target", choices=[t.name for t in TARGETS], help="one target only")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # (the readers' notes on clamped values, once a case)
    if args.target is None:
        common = ["--cases", str(args.cases), "--seed", str(args.seed)]
        runs = [
            subprocess.Popen(
                [sys.executable, __file__, "--target", target.name, *common],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            for target in TARGETS
        ]
        failed = 0
        for run in runs:
            output, _ = run.communicate()
            print(output, end="", flush=True)
            failed |= run.returncode
        return failed
    target = next(t for t in TARGETS if t.name == args.target)
    if target.missing():
        print(f"{target.name}: skipped, {target.missing()}")
        return 0
    result = fuzz(target, args.cases, args.seed)
    for defect in result["defects"]:
        print(defect, file=sys.stderr)
    print(
        f"{result['target']}: {result['cases']} cases ({result['ok']} read, {result['refused']} "
        f"refused with a GscError), {result['defect']} tracebacks, {result['hang']} hangs, "
        f"{result['over memory']} over the memory policy; {result['cases_per_second']} cases/s; "
        f"slowest case {result['slowest_case_seconds']} s (#{result['slowest_case']}, reading "
        f"only); peak RSS {result['peak_rss_above_base_mib']} MiB above the RSS after imports; "
        f"largest input {result['largest_input_bytes']} bytes"
    )
    return 1 if result["defect"] or result["hang"] or result["over memory"] else 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # (conftest's helpers)
    sys.exit(main())
