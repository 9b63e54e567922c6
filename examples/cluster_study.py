"""A study over several sequences on a Ray cluster: `gsc experiment` on each sequence, all at
once on the same cluster (each command a Ray driver whose runs are tasks on the cluster's
nodes), then one table of PWAS against random at the main budget, per sequence.

The sequences and the study folder must be on storage that every node sees at the same path
(docs/cluster.md). Options after `--` go to every `gsc experiment` as they are. Without
`--address` (each command then starts Ray for itself) or with `--executor local`, the
sequences run one after another on this machine instead. A rerun reuses
every finished run; the table lists the runs that failed.

Usage: python examples/cluster_study.py SEQ [SEQ ...] -o STUDY [--address auto]
           [--executor ray|local] [-- gsc experiment options]
  e.g. python examples/cluster_study.py /shared/data/office /shared/data/tabletop \\
           -o /shared/study --address auto -- --seeds 3 --cpus-per-run 2
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any


def experiment_command(seq: Path, out: Path, opts: argparse.Namespace, extra: list[str]) -> list:
    """The `gsc experiment` command of one sequence."""
    cmd = [sys.executable, "-m", "gscompress_cli", "experiment", str(seq), "-o", str(out)]
    cmd += ["--json", "--executor", opts.executor]
    if opts.executor == "ray" and opts.address:
        cmd += ["--address", opts.address]
    return cmd + extra


def summary_row(seq: Path, out: Path, result: dict[str, Any]) -> dict[str, Any]:
    """PWAS and random at the main budget (means over the seeds), wins and failed runs, from
    an experiment's folder and the output of its command."""
    rows = json.loads((out / "results.json").read_text())
    v = result["verdicts"]

    def mean_psnr(strategy: str) -> float | None:
        got = [
            r["psnr"]
            for r in rows
            if r["table"] == "table4" and r["strategy"] == strategy and r["psnr"] is not None
        ]
        return sum(got) / len(got) if got else None

    return {
        "sequence": seq.name,
        "budget": v["budget"],
        "pwas_psnr": mean_psnr("pwas"),
        "random_psnr": mean_psnr("random"),
        "pwas_wins": f"{v['pwas_beats_random_psnr']}/{v['seeds']}",
        "runs": result["steps"],
        "failed": len(result["failed"]),
    }


def cell(value: Any) -> str:
    return f"{value:.2f}" if isinstance(value, float) else str(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequences", type=Path, nargs="+")
    parser.add_argument("-o", "--output", type=Path, required=True, help="the study folder")
    parser.add_argument("--executor", choices=("ray", "local"), default="ray")
    parser.add_argument("--address", default=None, help="the Ray cluster (default: start one)")
    opts, extra = parser.parse_known_args()
    extra = [a for a in extra if a != "--"]
    names = [seq.name for seq in opts.sequences]
    if len(set(names)) != len(names):
        parser.error("two sequences have the same folder name (each gets its own study folder)")
    opts.output.mkdir(parents=True, exist_ok=True)
    outs = [opts.output / seq.name for seq in opts.sequences]
    commands = [
        experiment_command(s, o, opts, extra) for s, o in zip(opts.sequences, outs, strict=True)
    ]
    status = 0
    if opts.executor == "ray" and opts.address:  # every sequence's runs at once on the cluster
        procs = [subprocess.Popen(c, stdout=subprocess.PIPE, text=True) for c in commands]
        outputs = [(p.communicate()[0], p.returncode) for p in procs]
    else:
        outputs = []
        for c in commands:
            p = subprocess.run(c, stdout=subprocess.PIPE, text=True, check=False)
            outputs.append((p.stdout, p.returncode))
    table = []
    for seq, out, (text, code) in zip(opts.sequences, outs, outputs, strict=True):
        if code not in (0, 1):  # 1: the reports are written, some runs failed
            print(f"{seq}: gsc experiment failed (exit {code})", file=sys.stderr)
            status = 1
            continue
        table.append(summary_row(seq, out, json.loads(text)))
        status |= code
    keys = ["sequence", "budget", "pwas_psnr", "random_psnr", "pwas_wins", "runs", "failed"]
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(cell(row[k]) for k in keys) + " |" for row in table]
    (opts.output / "summary.md").write_text("\n".join(lines) + "\n")
    (opts.output / "summary.json").write_text(json.dumps(table, indent=1) + "\n")
    print("\n".join(lines))
    raise SystemExit(status)


if __name__ == "__main__":
    main()
