"""The fuzz policy's memory bound, and `gsc` run in a child process held to it.

The policy (docs/fuzzing.md): reading one input may take at most `memory_bound(input bytes)`
above what the process held after its imports, whatever it ends with. A reader that decodes a
bomb before refusing it breaks the bound even when its message is right.

`run_bounded` starts `python tests/bounded.py`, which imports what the command needs, measures
its address space and resident size, limits the address space (RLIMIT_AS) to what it has plus
the bound, runs the command in the same process and writes its peak RSS above the base to a
JSON file; `run_python_bounded` does the same for a few lines of Python (a reader that no
command runs alone, such as the viewer's renderer). Allocations past the limit fail
(MemoryError, which the CLI reports as "out of memory"), so a bomb makes the command fail
instead of taking the machine's memory.

    python tests/bounded.py --bound 300000000 --report r.json -- import-ply x.spz -o x.mcap
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

MEMORY_FLOOR_BYTES = 300_000_000
"""The bound for any input up to 15 MB: 300 MB above the RSS after imports."""

MEMORY_PER_INPUT_BYTE = 20
"""Above 15 MB, an input may take 20 times its own bytes."""

PRELOADED = (
    "numpy",
    "zstandard",
    "PIL.Image",
    "PIL.PngImagePlugin",
    "PIL.JpegImagePlugin",
    "PIL.WebPImagePlugin",
    "gscompress_cli.main",
    "gscompress.io.mcap_log",
    "gscompress.io.map_files",
    "gscompress.io.sog",
    "gscompress.datasets",
    "gscompress.pipeline",
)
"""Modules imported before the base is measured (what every reading command imports)."""


def memory_bound(input_bytes: int) -> int:
    """The most bytes above the RSS after imports that reading an input of `input_bytes` may
    take: max(300 MB, 20 x the input's bytes)."""
    return max(MEMORY_FLOOR_BYTES, MEMORY_PER_INPUT_BYTE * input_bytes)


def rss_bytes() -> int:
    """The process's resident size now, in bytes."""
    return _status("VmRSS")


def peak_rss_bytes() -> int:
    """The process's peak resident size since it started or since `reset_peak_rss`, in bytes:
    its memory's high-water mark (VmHWM; `getrusage`'s maximum can hold the RSS of the process
    that started this one, which a vfork lends it until the exec)."""
    return _status("VmHWM")


def reset_peak_rss() -> None:
    """Make the peak RSS the RSS now (Linux 4.0 and later), so that the next peak is one read's."""
    Path("/proc/self/clear_refs").write_text("5")


def _status(field: str) -> int:
    """A size in bytes from /proc/self/status (VmSize, VmRSS)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


@dataclass(frozen=True)
class Bounded:
    """What a bounded run did.

    Attributes:
        returncode: the command's exit code.
        stderr: what it wrote on stderr.
        peak_above_base: peak RSS above the RSS after imports (bytes).
        bound: the bound it ran under (bytes).
    """

    returncode: int
    stderr: str
    peak_above_base: int
    bound: int

    @property
    def lines(self) -> list[str]:
        """The non-empty lines of stderr."""
        return [line for line in self.stderr.splitlines() if line.strip()]


def run_bounded(
    args: list[str | bytes],
    bound: int,
    *,
    cwd: Path,
    preload: tuple[str, ...] = (),
    warnings_as_errors: bool = True,
    timeout: float = 300,
) -> Bounded:
    """Run `gsc ARGS` in a child process whose address space may grow by at most `bound` bytes
    after its imports (`PRELOADED` and `preload`); numpy's RuntimeWarnings are errors there
    unless `warnings_as_errors` is False."""
    report = cwd / ".bounded.json"
    report.unlink(missing_ok=True)
    command: list[str | bytes] = [sys.executable]
    if warnings_as_errors:
        command += ["-W", "error::RuntimeWarning"]
    command += [__file__, "--bound", str(bound), "--report", str(report)]
    command += [item for name in preload for item in ("--preload", name)]
    env = dict(os.environ, MALLOC_ARENA_MAX="2", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    done = subprocess.run(
        [*command, "--", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        timeout=timeout,
    )
    stderr = done.stderr.decode("utf-8", "backslashreplace")
    measured = json.loads(report.read_text()) if report.is_file() else {}
    return Bounded(done.returncode, stderr, int(measured.get("peak_above_base", -1)), bound)


def run_python_bounded(setup: str, code: str, bound: int, *, cwd: Path) -> Bounded:
    """Run Python `setup` (imports, a warm-up), then `code` under the same limit as
    `run_bounded` (`bound` bytes above the address space after `setup`), in a child process;
    numpy's RuntimeWarnings are errors there."""
    report = cwd / ".bounded.json"
    report.unlink(missing_ok=True)
    command = [sys.executable, "-W", "error::RuntimeWarning", __file__, "--bound", str(bound)]
    command += ["--report", str(report), "--setup", setup, "--code", code]
    env = dict(os.environ, MALLOC_ARENA_MAX="2", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, timeout=300)
    measured = json.loads(report.read_text()) if report.is_file() else {}
    stderr = done.stderr.decode("utf-8", "backslashreplace")
    return Bounded(done.returncode, stderr, int(measured.get("peak_above_base", -1)), bound)


def main() -> int:
    """The child: imports (or `--setup`), the limit, the command (or `--code`), the report."""
    parser = argparse.ArgumentParser()
    parser.add_argument("--bound", type=int, required=True)
    parser.add_argument("--report", type=Path, required=True)
    parser.add_argument("--preload", action="append", default=[])
    parser.add_argument("--setup", default="")
    parser.add_argument("--code")
    parser.add_argument("args", nargs=argparse.REMAINDER)
    options = parser.parse_args()
    names: dict[str, object] = {}
    for name in (*PRELOADED, *options.preload):
        importlib.import_module(name)
    exec(options.setup, names)
    from gscompress_cli.main import cli

    base = rss_bytes()
    reset_peak_rss()
    limit = _status("VmSize") + options.bound
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    args = options.args[1:] if options.args[:1] == ["--"] else options.args
    try:
        if options.code is not None:
            exec(options.code, names)
        else:
            cli.main([os.fsdecode(a) for a in args], prog_name="gsc")
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        peak = peak_rss_bytes()
        options.report.write_text(json.dumps({"peak_above_base": max(peak - base, 0)}))
    return code


if __name__ == "__main__":
    sys.exit(main())
