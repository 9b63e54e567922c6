"""Benchmark the folding commands of two source trees, alternating in one call.

`gsc prune --keep 0.3` and `gsc share` (a fraction, `--budget 0.2`, and a byte budget, whose
search folds once per step) fold what they leave out (`gscompress.ops.fold`). This runs them,
with `gsc info` of the same log as the reference, from two checkouts (--old, e.g. a `git
worktree` of the commit before a change, and --new, by default this one), each command in a
fresh interpreter, old and new one after the other (which goes first alternates by round). It
prints one JSON object per command and tree: the median wall time, the time of the command
itself (`run_s`: imports excluded) and the process's CPU time (user + system, every thread;
what other load on the machine changes least). The summary gives prune / info and share / info
on each tree and new / old for each command, and says whether both trees wrote the same bytes
(each tree's version string, which a log records, left out).

Logs: bench/offline.py's log of N Gaussians (default 1,000,000; fraction budgets only: there
a byte budget's search of the old tree folds a million Gaussians some 15 times, about a
minute), one of 100,000 (all four commands) and any --log (a real map; all four). Times depend
on the load: the load average is recorded at the start and the end.

Usage: python bench/fold.py --old DIR [--new DIR] [--gaussians 1000000] [--small 100000]
       [--budget-bytes 200kB] [--log REAL.mcap ...] [--repeat 3] [--work DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from offline import make_log  # (bench/offline.py's log: the same map)

CHILD = """
import json, resource, sys, time
t0 = time.perf_counter()
from gscompress_cli.main import cli
import gscompress.pipeline
t1 = time.perf_counter()
try:
    cli(json.loads(sys.argv[1]))
except SystemExit as e:
    assert not e.code, e
usage = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"import_s": t1 - t0, "run_s": time.perf_counter() - t1,
                  "cpu_s": usage.ru_utime + usage.ru_stime}))
"""

OUTPUTS = {"prune": "p.mcap", "share": "s.mcap", "share-bytes": "b.mcap"}


def shim(tree: Path, where: Path) -> Path:
    """A folder that imports the packages of source tree `tree` (gscompress, and cli/ and
    schemas/ under their installed names)."""
    where.mkdir(parents=True, exist_ok=True)
    for name, folder in (
        ("gscompress", "gscompress"),
        ("gscompress_cli", "cli"),
        ("gscompress_schemas", "schemas"),
    ):
        link = where / name
        if not link.exists():
            link.symlink_to(tree.resolve() / folder)
    return where


def commit(tree: Path) -> str:
    """The tree's commit, with "+dirty" when it has changes not committed."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(tree), *args], capture_output=True, text=True, check=True
        ).stdout.strip()

    return git("rev-parse", "--short", "HEAD") + ("+dirty" if git("status", "--porcelain") else "")


def commands(log: Path, budget_bytes: str | None) -> dict[str, list[str]]:
    """The commands run on `log` (outputs relative: each tree writes into its own folder)."""
    out = {
        "info": ["info", str(log)],
        "prune": ["prune", str(log), "--keep", "0.3", "-o", OUTPUTS["prune"]],
        "share": ["share", str(log), OUTPUTS["share"], "--budget", "0.2"],
    }
    if budget_bytes:
        out["share-bytes"] = ["share", str(log), OUTPUTS["share-bytes"], "--budget", budget_bytes]
    return out


def version(shim_dir: Path) -> bytes:
    """The version string that the tree's logs record."""
    out = subprocess.run(
        [sys.executable, "-c", "import gscompress; print(gscompress.__version__)"],
        env={**os.environ, "PYTHONPATH": str(shim_dir)},
        cwd=shim_dir,  # (not a folder whose own gscompress would be imported first)
        capture_output=True,
        text=True,
        check=True,
    )
    return out.stdout.strip().encode()


def run_child(shim_dir: Path, cwd: Path, args: list[str]) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(shim_dir)}
    for name in OUTPUTS.values():
        (cwd / name).unlink(missing_ok=True)
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(args)],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    result: dict[str, float] = json.loads(out.stdout.strip().splitlines()[-1])
    result["wall_s"] = time.perf_counter() - t0
    return result


def load() -> list[float]:
    return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", type=Path, required=True, help="source tree before the change")
    parser.add_argument("--new", type=Path, default=Path(__file__).resolve().parents[1])
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--small", type=int, default=100_000, help="Gaussians of the 2nd log")
    parser.add_argument("--budget-bytes", default="200kB", help="byte budget of share-bytes")
    parser.add_argument("--log", type=Path, action="append", default=[], help="a real map")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--work", type=Path, default=None, help="keep the logs made here")
    parser.add_argument("--out", type=Path, default=None, help="also write the results here")
    opts = parser.parse_args()
    trees = {"old": opts.old, "new": opts.new}
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        work = opts.work or tmp
        work.mkdir(parents=True, exist_ok=True)
        logs: list[tuple[Path, str | None]] = []
        for n, budget in ((opts.gaussians, None), (opts.small, opts.budget_bytes)):
            if n == 0:  # (--gaussians 0 / --small 0: not this one)
                continue
            path = work / f"random_{n}.mcap"
            if not path.exists():
                make_log(path, n)
            logs.append((path, budget))
        logs += [(log.resolve(), opts.budget_bytes) for log in opts.log]
        shims = {name: shim(tree, tmp / f"shim_{name}") for name, tree in trees.items()}
        versions = {name: version(shims[name]) for name in trees}
        cwds = {name: tmp / name for name in trees}
        for cwd in cwds.values():
            cwd.mkdir()
        info: dict[str, Any] = {"load_start": load()}
        info.update({f"{k}_commit": commit(t) for k, t in trees.items()})
        runs: dict[tuple[str, str, str], list[dict[str, float]]] = {}
        same: dict[tuple[str, str], bool] = {}
        for round_ in range(opts.repeat):
            order = ("old", "new") if round_ % 2 == 0 else ("new", "old")
            for log, budget in logs:
                for name, args in commands(log, budget).items():
                    for tree in order:
                        row = run_child(shims[tree], cwds[tree], args)
                        runs.setdefault((log.name, name, tree), []).append(row)
                    if name in OUTPUTS:
                        written = [
                            (cwds[t] / OUTPUTS[name]).read_bytes().replace(versions[t], b"")
                            for t in trees
                        ]
                        same[(log.name, name)] = same.get((log.name, name), True) and (
                            written[0] == written[1]
                        )
        info["load_end"] = load()
    rows: list[dict[str, Any]] = []
    for (log_name, name, tree), results in runs.items():
        line = {"log": log_name, "command": name, "tree": tree, "commit": info[f"{tree}_commit"]}
        for key in ("wall_s", "run_s", "cpu_s"):
            line[key] = round(statistics.median(r[key] for r in results), 3)
            line[f"{key}_all"] = [round(r[key], 3) for r in results]
        rows.append(line)
        print(json.dumps(line), flush=True)

    def median(log_name: str, name: str, tree: str, key: str = "wall_s") -> float:
        return next(
            r[key] for r in rows if (r["log"], r["command"], r["tree"]) == (log_name, name, tree)
        )

    per_log: dict[str, dict[str, object]] = {}
    for log, budget in logs:
        names = list(commands(log, budget))
        figures: dict[str, object] = {}
        for key in ("wall_s", "run_s", "cpu_s"):
            figures[key] = {
                **{
                    tree: {
                        f"{name}/info": round(
                            median(log.name, name, tree, key) / median(log.name, "info", tree, key),
                            2,
                        )
                        for name in names[1:]
                    }
                    for tree in trees
                },
                "new/old": {
                    name: round(
                        median(log.name, name, "new", key) / median(log.name, name, "old", key), 3
                    )
                    for name in names
                },
            }
        figures["same_bytes"] = {name: same[(log.name, name)] for name in names[1:]}
        per_log[log.name] = figures
    summary = {"summary": "folding commands, old and new", **info, "logs": per_log}
    print(json.dumps(summary, indent=1))
    if opts.out:
        opts.out.write_text(json.dumps({"rows": rows, "summary": summary}, indent=2))


if __name__ == "__main__":
    main()
