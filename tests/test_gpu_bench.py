"""The GPU benchmark scripts of bench/gpu, run on the CPU: setup.sh's refusals, table.sh's smoke
path end to end (the same JSON a GPU machine writes), and a run stopped at its deadline."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GPU_BENCH = ROOT / "bench" / "gpu"
PHASES = ("tracking", "densification", "mapping", "pwas", "pruning", "refinement", "wall")

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="the scripts need bash")


def script_env(tmp_path: Path, **extra: str) -> dict[str, str]:
    """The scripts' environment: this interpreter's torch, every output under tmp_path."""
    env = dict(os.environ)
    env.update(
        GSC_GPU_PYTHON=sys.executable,
        GSC_GPU_BUILD=str(tmp_path / "build"),
        GSC_GPU_WHEELS=str(tmp_path / "wheels"),
        OUT=str(tmp_path / "out"),
        OMP_NUM_THREADS="1",
        **extra,
    )
    return env


def bash(args: list[str], env: dict[str, str], timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["bash", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.slow
def test_setup_stops_in_one_line_without_the_wheels_or_cuda(tmp_path):
    env = script_env(tmp_path)
    done = bash([str(GPU_BENCH / "setup.sh")], env)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        f"setup.sh: no gsplat wheel in {tmp_path / 'wheels'}: run bench/gpu/fetch_wheels.sh "
        "where pip reaches PyPI and carry bench/gpu/wheels"
    ]
    import torch

    if torch.cuda.is_available():
        return  # (the refusal below is for a machine without a GPU)
    (tmp_path / "wheels").mkdir()
    for name in ("gsplat", "mcap", "mcap_protobuf_support", "foxglove_schemas_protobuf"):
        (tmp_path / "wheels" / f"{name}-1.0-py3-none-any.whl").touch()
    for name in ("zstandard", "lz4", "protobuf"):
        (tmp_path / "wheels" / f"{name}-1.0-cp312-cp312-manylinux2014_x86_64.whl").touch()
    done = bash([str(GPU_BENCH / "setup.sh")], env)
    assert done.returncode == 1
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("setup.sh: no CUDA: torch sees no GPU")
    assert not (tmp_path / "build" / "venv").exists()  # it stopped before doing anything


@pytest.mark.slow
def test_table_smoke_writes_the_gpu_json(tmp_path):
    # no wheels (none are needed on the CPU) and no staged data: the sequence where it is, else
    # the synthetic room
    env = script_env(tmp_path, GSC_DATA=str(tmp_path / "no_data"))
    done = bash([str(GPU_BENCH / "table.sh"), "--cpu-smoke"], env)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == [
        "gpu_tabletop.json",
        "gpu_tabletop.log",
        "gpu_tests.txt",
        "setup.json",
    ]
    setup = json.loads((out / "setup.json").read_text())
    assert setup["mode"] == "cpu-smoke"
    assert set(setup["steps_s"]) == {"files", "venv", "wheels", "gscompress"}
    report = json.loads((out / "gpu_tabletop.json").read_text())
    assert report["mode"] == "cpu-smoke" and report["setup"] == setup
    assert (report["size"], report["preset"], report["backend"]) == ([64, 48], "tiny", "cpu")
    assert report["gpu_tests"].startswith("exit 0 in ")  # (all skipped without CUDA)
    assert report["elapsed_s"] is not None and report["concurrent_runs"] == 1
    assert set(report["runs"]) == {"unpruned", "pwas"}
    for run in report["runs"].values():
        assert run["frames"] == run["frames_total"] == 3 and not run["interrupted"]
        assert run["render_backend"] == "cpu" and run["device"] == "cpu"
        assert run["seconds_per_frame"] > 0 and run["psnr"] > 10 and 0 < run["ssim"] <= 1
        assert run["ate_rmse_cm"] is not None and run["gaussians"] > 0
        assert all(phase in run["ms_per_frame"] for phase in PHASES)
        assert run["ms_per_frame"]["tracking"] > 0 and run["ms_per_frame"]["mapping"] > 0
        assert run["peak_gpu_mib"] == {"run": None, "eval": None, "run_reserved": None}
    versus = report["versus_unpruned"]["pwas"]
    kept = report["runs"]["pwas"]["gaussians"] / report["runs"]["unpruned"]["gaussians"]
    assert versus["gaussian_reduction_percent"] == pytest.approx(100 * (1 - kept), abs=0.05)
    log = (out / "gpu_tabletop.log").read_text()
    assert "| unpruned | 3/3 |" in log and "| pwas | 3/3 |" in log  # the rows as they came


@pytest.mark.slow
def test_a_run_past_its_deadline_stops_and_is_scored_as_far_as_it_got(tmp_path):
    from gscompress.datasets.synthetic import write_synthetic_sequence
    from gscompress.slam.config import preset, save_config

    seq = write_synthetic_sequence(tmp_path / "room", frames=3, size=(64, 48))
    config = save_config(preset("tiny").with_overrides(backend="torch"), tmp_path / "run.yaml")
    record_path = tmp_path / "run.json"
    child = [
        sys.executable,
        str(GPU_BENCH / "table.py"),
        "--child",
        "unpruned",
        str(seq),
        "--log",
        str(tmp_path / "run.mcap"),
        "--config",
        str(config),
        "--frames",
        "all",
        "--device",
        "cpu",
        "--deadline",
        "0",
        "--threads",
        "1",
        "--json-out",
        str(record_path),
    ]
    done = subprocess.run(child, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "[unpruned] deadline: stopped after frame 1 of 3" in done.stdout
    record = json.loads(record_path.read_text())
    assert record["interrupted"] and (record["frames"], record["frames_total"]) == (1, 3)
    assert record["eval_views"] == 1 and record["psnr"] > 10 and record["gaussians"] > 0
    assert record["render_backend"] == "torch"
