"""The GPU table of `gsc slam`: unpruned and PWAS-pruned runs of one sequence, in one JSON.

For one sequence (by default at 640x480 with the `paper` preset and the gsplat backend), runs
`gscompress.pipeline.slam_file` once per name of `--runs` (bench/pruning.py's runs: `unpruned`,
`pwas`, `opacity`, `pwas@KEEP`), each in a process of its own so that its peak GPU memory is its
own, and scores each log as bench/slam.py does (`gsc eval` without LPIPS). For every run the
JSON holds: seconds per frame (wall), the mean milliseconds per frame of each phase from the
log's per-frame stats (tracking, densification, mapping, PWAS, pruning, the final refinement and
logging, as bench/pruning.py breaks them down; and bench/slam.py's means after the first frame),
ATE, PSNR/SSIM, depth L1, Gaussians (at the end and the most during the run), and
`torch.cuda.max_memory_allocated` (and reserved) during the run and during its evaluation; then
each pruned run against the unpruned one (bench/pruning.py's comparison).

Sized for a GPU machine lent for minutes: everything ends by `--deadline-s` (a run still going
then stops after its current frame, and its log is scored as far as it got, marked
`interrupted`), the JSON is rewritten after every run, and each run prints its progress every
10 frames. `--parallel` runs the runs at once on the one GPU (their seconds per frame then share
it, and the JSON says so).

`--cpu-smoke` runs the same steps on the CPU at a tiny size (3 frames at 64x48, `tiny` preset,
cpu backend; the synthetic room where the sequence is absent), so that this script is tested
where there is no GPU; its JSON has the same shape, with no GPU memory.

Sequences: a folder, or a short name of bench/gpu/sequences.txt (tabletop, frag1, icl), looked
for in $GSC_DATA, bench/gpu/data (bench/gpu/stage_data.sh), shared/data and ../shared/data.

Usage (bench/gpu/table.sh and bench/gpu/sequences.sh run it after bench/gpu/setup.sh):
    python bench/gpu/table.py tabletop --json-out OUT/gpu_tabletop.json --deadline-s 400
    python bench/gpu/table.py icl --parallel            # frames 0:120, both runs at once
    python bench/gpu/table.py tabletop --cpu-smoke
    python bench/gpu/table.py SEQ_FOLDER --frames 0:20 --set mapping.final_iters=1000
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import yaml

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.io.mcap_log import LogReader
from gscompress.pipeline import slam_file
from gscompress.pipeline.slam_run.options import SlamOptions
from gscompress.slam.config import resolve_config, save_config
from gscompress.threads import use_threads

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bench"))  # bench/slam.py and bench/pruning.py
from pruning import breakdown, compare, read_stats, run_overrides  # noqa: E402
from slam import evaluate  # noqa: E402

SEQUENCES = Path(__file__).with_name("sequences.txt")
MODES: dict[str, dict[str, Any]] = {
    "gpu": {"size": (640, 480), "preset": "paper", "backend": "gsplat", "device": "cuda"},
    "cpu-smoke": {"size": (64, 48), "preset": "tiny", "backend": "cpu", "device": "cpu"},
}
"""What a run is made of in each mode (`--size`, `--preset` override the first two)."""
SMOKE_FRAMES = "0:3"
MIB = 2**20


def sequence_table() -> dict[str, tuple[str, str]]:
    """Short name -> (folder name, frames), from bench/gpu/sequences.txt."""
    rows = [line.split() for line in SEQUENCES.read_text(encoding="utf-8").splitlines()]
    return {row[0]: (row[1], row[2]) for row in rows if row and not row[0].startswith("#")}


def data_folders() -> list[Path]:
    """Where sequences are looked for, in order."""
    given = [Path(p) for p in os.environ.get("GSC_DATA", "").split(os.pathsep) if p]
    return [*given, ROOT / "bench/gpu/data", ROOT / "shared/data", ROOT.parent / "shared/data"]


def find_sequence(name: str) -> tuple[Path | None, str, str]:
    """(the sequence folder or None, its name, its default frames) of a folder or short name."""
    table = sequence_table()
    frames_of = {folder: frames for folder, frames in table.values()}
    if Path(name).is_dir():
        return Path(name), Path(name).name, frames_of.get(Path(name).name, "all")
    folder, frames = table.get(name, (name, frames_of.get(name, "all")))
    for base in data_folders():
        if (base / folder).is_dir():
            return base / folder, folder, frames
    return None, folder, frames


def commit() -> dict[str, Any]:
    """The checkout's commit and whether tracked files differ from it; where the tree came
    without its git folder, $GSC_COMMIT, else the one stage_data.sh wrote beside the data."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        staged = ROOT / "bench/gpu/data/commit.txt"
        if os.environ.get("GSC_COMMIT"):
            return {"commit": os.environ["GSC_COMMIT"], "dirty": None, "commit_from": "GSC_COMMIT"}
        if staged.is_file():
            head, _, dirty = staged.read_text(encoding="utf-8").partition(" ")
            return {
                "commit": head.strip(),
                "dirty": dirty.strip() == "dirty",
                "commit_from": "bench/gpu/data/commit.txt",
            }
        return {"commit": "unknown", "dirty": None, "commit_from": None}
    return {"commit": head, "dirty": bool(status.strip()), "commit_from": "git"}


def machine(device: str, threads: int) -> dict[str, Any]:
    """The torch, CUDA, GPU and gsplat this table ran with."""
    import torch

    try:
        gsplat = version("gsplat")
    except PackageNotFoundError:
        gsplat = None
    cuda = device == "cuda" and torch.cuda.is_available()
    return {
        "gpu": torch.cuda.get_device_name(0) if cuda else None,
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "gsplat": gsplat,
        "cpus": os.cpu_count(),
        "threads_per_run": threads,
    }


def write_json(report: dict[str, Any], path: Path) -> None:
    """Write the report whole (a copy renamed into place: a reader never sees half of it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def table_lines(runs: dict[str, dict[str, Any]]) -> list[str]:
    """A Markdown table of the finished runs."""
    lines = [
        "| run | frames | s/frame | tracking ms | mapping ms | refinement ms | Gaussians | "
        "PSNR dB | SSIM | ATE cm | peak GPU MiB |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, run in runs.items():
        if "error" in run:
            lines.append(f"| {name} | {run['error']} |")
            continue
        ms, ate, peak = run["ms_per_frame"], run["ate_rmse_cm"], run["peak_gpu_mib"]["run"]
        frames = f"{run['frames']}/{run['frames_total']}" + (" (stopped)" * run["interrupted"])
        lines.append(
            f"| {name} | {frames} | {run['seconds_per_frame']:.3f} | {ms['tracking']:.0f} | "
            f"{ms['mapping']:.0f} | {ms['refinement']:.0f} | {run['gaussians']} | "
            f"{run['psnr']:.2f} | {run['ssim']:.3f} | {'-' if ate is None else f'{ate:.3f}'} | "
            f"{'-' if peak is None else f'{peak:.0f}'} |"
        )
    return lines


# --- one run (a process of its own) --------------------------------------------------------


def run_one(
    name: str,
    seq: Path,
    log_path: Path,
    config_path: Path,
    frames: str,
    device: str,
    deadline: float,
) -> dict[str, Any]:
    """Run SLAM with the config at `config_path`, stopping after the frame that ends past
    `deadline` (time.time()), and score the log, as far as it got, with its phase times and
    the peak GPU memory of the run and of its evaluation."""
    import torch

    cuda = device == "cuda"
    stopped: list[int] = []  # the frame after which the deadline stopped the run

    def progress(done: int, total: int, stats: dict[str, Any]) -> None:
        if done == 1 or done % 10 == 0 or done == total:
            print(
                f"[{name}] frame {done}/{total}: {stats['seconds'] / done:.2f} s/frame, "
                f"{stats.get('gaussians')} Gaussians",
                flush=True,
            )
        if done < total and time.time() > deadline:
            print(f"[{name}] deadline: stopped after frame {done} of {total}", flush=True)
            stopped.append(done)
            raise KeyboardInterrupt  # slam_file closes the log, valid, marked interrupted

    def peak() -> dict[str, float] | None:
        if not cuda:
            return None
        used = torch.cuda.max_memory_allocated() / MIB, torch.cuda.max_memory_reserved() / MIB
        torch.cuda.reset_peak_memory_stats()
        return {"allocated": round(used[0], 1), "reserved": round(used[1], 1)}

    if cuda:
        torch.cuda.reset_peak_memory_stats()
    started = time.perf_counter()
    try:
        slam_file(
            seq,
            log_path,
            SlamOptions(config_path=config_path, frames=frames),
            device=device,
            command=f"bench/gpu/table.py ({name})",
            force=True,
            progress=progress,
        )
    except KeyboardInterrupt:
        if not stopped:  # Ctrl-C
            raise
    wall = time.perf_counter() - started
    run_peak = peak()
    with LogReader(log_path) as reader:
        results = dict(reader.metadata.results)
    record = evaluate(log_path, seq)  # bench/slam.py: gsc eval's metrics, counts, phase means
    eval_peak = peak()
    record.update(
        frames_total=results["frames_total"],
        interrupted=results["interrupted"],
        device=results["device"],
        render_backend=results["render_backend"],
        seconds_per_frame=results["seconds_per_frame"],
        wall_s=round(wall, 2),
        ms_per_frame=breakdown(read_stats(log_path), results["seconds_per_frame"]),
        peak_gpu_mib={
            "run": run_peak and run_peak["allocated"],
            "eval": eval_peak and eval_peak["allocated"],
            "run_reserved": run_peak and run_peak["reserved"],
        },
        torch_threads=torch.get_num_threads(),
    )
    return record


def child(opts: argparse.Namespace) -> None:
    """`--child NAME`: one run, its record written to --json-out."""
    use_threads(opts.threads)
    record = run_one(
        opts.child,
        Path(opts.seq),
        Path(opts.log),
        Path(opts.config),
        opts.frames,
        opts.device,
        opts.deadline,
    )
    write_json(record, Path(opts.json_out))


# --- the table ------------------------------------------------------------------------------


def launch(name: str, seq: Path, work: Path, opts: argparse.Namespace, threads: int) -> Any:
    """Start the process of one run (its output goes to ours, each line marked by its name)."""
    command = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--child",
        name,
        str(seq),
        "--log",
        str(work / f"{name}.mcap"),
        "--config",
        str(work / f"{name}.yaml"),
        "--frames",
        opts.frames,
        "--device",
        opts.device,
        "--deadline",
        str(opts.deadline),
        "--threads",
        str(threads),
        "--json-out",
        str(work / f"{name}.json"),
    ]
    (work / f"{name}.json").unlink(missing_ok=True)
    return subprocess.Popen(command)


def finish(name: str, process: Any, work: Path, deadline: float) -> dict[str, Any]:
    """Wait for a run's process (killing it a grace period past the deadline) and read its
    record."""
    grace = 45.0  # for the frame under way and the evaluation
    try:
        code = process.wait(timeout=max(deadline + grace - time.time(), 1.0))
    except subprocess.TimeoutExpired:
        process.terminate()
        process.wait()
        return {"error": f"killed {grace:.0f} s past the deadline"}
    path = work / f"{name}.json"
    if code != 0 or not path.is_file():
        return {"error": f"the run's process failed (exit code {code}; see its output)"}
    record: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return record


def prepare(opts: argparse.Namespace) -> tuple[Path, str, Path]:
    """The sequence (the synthetic room for a smoke run without it), its name and the folder of
    the logs; sets opts.frames to the sequence's default where none was given."""
    seq, name, frames = find_sequence(opts.seq)
    work = Path(opts.work) / name
    work.mkdir(parents=True, exist_ok=True)
    if opts.cpu_smoke:
        opts.frames = opts.frames or SMOKE_FRAMES
        if seq is None:
            seq = work / "synthetic"
            if not seq.is_dir():
                write_synthetic_sequence(seq, frames=3, size=MODES["cpu-smoke"]["size"])
            name += " (absent: the synthetic room)"
    elif seq is None:
        places = ", ".join(str(p) for p in data_folders())
        raise SystemExit(
            f"table.py: no sequence {name} in {places}: run bench/gpu/stage_data.sh "
            f"{opts.seq} where the data is and carry bench/gpu/data"
        )
    opts.frames = opts.frames or frames
    return seq, name, work


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seq", nargs="?", default="tabletop", help="folder or short name")
    parser.add_argument("--frames", default=None, help="default: bench/gpu/sequences.txt's")
    parser.add_argument("--runs", default="unpruned,pwas", help="bench/pruning.py's run names")
    parser.add_argument("--size", default=None, help="WxH (default 640x480; smoke 64x48)")
    parser.add_argument("--preset", default=None, help="default paper (smoke: tiny)")
    parser.add_argument("--set", action="append", default=[], help="dotted.key=yaml_value")
    parser.add_argument("--parallel", action="store_true", help="all runs at once on the GPU")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads per run")
    parser.add_argument("--deadline-s", type=float, default=400.0, help="for the whole table")
    parser.add_argument("--cpu-smoke", action="store_true", help="tiny, on the CPU")
    parser.add_argument("--json-out", default=None, help="default: OUT/gpu_NAME.json")
    parser.add_argument("--setup-json", default=None, help="setup.sh's record, to include")
    parser.add_argument("--gpu-tests", default=None, help="the GPU tests' outcome, to include")
    default_work = Path(os.environ.get("GSC_GPU_BUILD", ROOT / "bench/gpu/.build")) / "runs"
    parser.add_argument("--work", default=str(default_work), help="where the logs go")
    for hidden in ("--child", "--log", "--config", "--device", "--deadline"):
        parser.add_argument(hidden, default=None, help=argparse.SUPPRESS)
    opts = parser.parse_args()
    if opts.child:
        opts.deadline = float(opts.deadline)
        child(opts)
        return
    table(opts)


def table(opts: argparse.Namespace) -> None:
    """Run every run of the table and keep its JSON up to date (see the module doc)."""
    started = time.time()
    opts.deadline = started + opts.deadline_s
    settings = settings_of(opts)
    seq, name, work = prepare(opts)
    names = opts.runs.split(",")
    concurrent = len(names) if opts.parallel else 1
    threads = opts.threads or (1 if opts.cpu_smoke else max((os.cpu_count() or 1) // concurrent, 1))
    shared = write_configs(opts, settings, names, work)
    out = Path(os.environ.get("OUT", ROOT / "bench_out/gpu"))
    json_out = Path(opts.json_out or out / f"gpu_{Path(opts.seq).name}.json")
    setup = Path(opts.setup_json) if opts.setup_json else None
    report: dict[str, Any] = {
        "what": "bench/gpu/table.py",
        "mode": "cpu-smoke" if opts.cpu_smoke else "gpu",
        **commit(),
        "sequence": name,
        "path": str(seq),
        "frames": opts.frames,
        "size": list(settings["size"]),
        "preset": settings["preset"],
        "backend": settings["backend"],
        "overrides": shared,
        "machine": machine(opts.device, threads),
        "concurrent_runs": concurrent,
        "deadline_s": opts.deadline_s,
        "setup": json.loads(setup.read_text()) if setup and setup.is_file() else None,
        "gpu_tests": opts.gpu_tests,
        "runs": {},
        "versus_unpruned": {},
        "elapsed_s": None,
    }
    write_json(report, json_out)
    print(f"table.py: {name} ({opts.frames}) {settings}, runs {names}, JSON {json_out}", flush=True)
    run_all(names, seq, work, opts, threads, report, json_out)
    report["elapsed_s"] = round(time.time() - started, 1)
    write_json(report, json_out)
    print("\n".join(table_lines(report["runs"])))
    print(json.dumps({"versus_unpruned": report["versus_unpruned"], "json": str(json_out)}))
    failed = [n for n, r in report["runs"].items() if "error" in r]
    if failed:
        raise SystemExit(f"table.py: {', '.join(failed)} did not finish (their records say why)")


def settings_of(opts: argparse.Namespace) -> dict[str, Any]:
    """The mode's size, preset, backend and device with the options' changes (opts.device set);
    a GPU table stops at once where torch sees no GPU."""
    settings = dict(MODES["cpu-smoke" if opts.cpu_smoke else "gpu"])
    if opts.size:
        width, height = opts.size.split("x")
        settings["size"] = (int(width), int(height))
    settings["preset"] = opts.preset or settings["preset"]
    opts.device = settings["device"]
    if opts.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise SystemExit("table.py: torch sees no CUDA GPU (--cpu-smoke runs on the CPU)")
    return settings


def write_configs(
    opts: argparse.Namespace, settings: dict[str, Any], names: list[str], work: Path
) -> dict[str, Any]:
    """Each run's config, saved as work/RUN.yaml; returns the --set overrides they share."""
    shared = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in opts.set)}
    base = resolve_config(settings["preset"], size=settings["size"])
    base = base.with_overrides(backend=settings["backend"], **shared)
    for run_name in names:
        save_config(base.with_overrides(**run_overrides(run_name)), work / f"{run_name}.yaml")
    return shared


def run_all(
    names: list[str],
    seq: Path,
    work: Path,
    opts: argparse.Namespace,
    threads: int,
    report: dict[str, Any],
    json_out: Path,
) -> None:
    """The runs, at once (--parallel) or one after the other, each recorded in the report (and
    the report written) as it finishes."""
    runs: dict[str, dict[str, Any]] = report["runs"]

    def record(run_name: str, result: dict[str, Any]) -> None:
        runs[run_name] = result
        report["versus_unpruned"] = compare({n: r for n, r in runs.items() if "error" not in r})
        write_json(report, json_out)

    if opts.parallel:
        processes = {n: launch(n, seq, work, opts, threads) for n in names}
        for run_name, process in processes.items():
            record(run_name, finish(run_name, process, work, opts.deadline))
        return
    print("\n".join(table_lines({})), flush=True)
    for run_name in names:
        if time.time() > opts.deadline - 20:
            record(run_name, {"error": "not started: the deadline was near"})
        else:
            process = launch(run_name, seq, work, opts, threads)
            record(run_name, finish(run_name, process, work, opts.deadline))
        print(table_lines({run_name: runs[run_name]})[-1], flush=True)


if __name__ == "__main__":
    main()
