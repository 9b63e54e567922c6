"""The example scripts run on a real (tiny) log and say what the log holds."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.io.mcap_log import TOPIC_POSE, LogReader
from gscompress.io.trajectory import read_tum_trajectory
from gscompress.pipeline import share_log, slam_file
from gscompress.pipeline.share.options import ShareOptions
from gscompress.pipeline.slam_run.options import SlamOptions

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    seq = write_synthetic_sequence(tmp_path_factory.mktemp("seq") / "room", 6, (64, 48))
    log = tmp_path_factory.mktemp("run") / "run.mcap"
    slam_file(seq, log, SlamOptions(preset="tiny"))
    return seq, log


def example(name: str, *args: object) -> str:
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_the_demo_stops_at_a_failed_step_with_gscs_one_line(tmp_path: Path) -> None:
    """A step that fails ends the demo with gsc's own message and exit status, no traceback."""
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / "demo.py"), "--out", tmp_path / "demo", "--frames", "0"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr  # (gsc synth's usage error)
    assert "Traceback" not in proc.stderr
    assert (
        proc.stderr.strip().splitlines()
        == [line for line in proc.stderr.strip().splitlines() if line.startswith("Error:")]
        != []
    )
    assert "$ gsc synth" in proc.stdout and "$ gsc slam" not in proc.stdout


def test_read_log_lists_the_map_and_writes_the_trajectory(
    run: tuple[Path, Path], tmp_path: Path
) -> None:
    _, log = run
    out = example("read_log.py", log, "--tum", tmp_path / "t.txt", "--top", 3)
    with LogReader(log) as reader:
        gaussians = reader.read_map()
        stamps, poses = reader.read_poses(TOPIC_POSE)
    assert f"map: {len(gaussians)} Gaussians" in out
    top = gaussians.ids[np.argsort(-gaussians.importance, kind="stable")[:3]]
    listed = [int(line.split()[1].rstrip(":")) for line in out.splitlines() if " id " in line]
    assert listed == [int(i) for i in top]
    written = read_tum_trajectory(tmp_path / "t.txt")
    np.testing.assert_allclose(written.timestamps, stamps / 1e9)
    np.testing.assert_allclose(written.T_world_cam, poses, atol=1e-9)


def test_budget_sweep_counts_the_bytes_a_share_of_each_budget_writes(
    run: tuple[Path, Path], tmp_path: Path
) -> None:
    seq, log = run
    rows_file = tmp_path / "rows.json"
    example(
        "budget_sweep.py",
        log,
        "--seq",
        seq,
        "--budgets",
        "0.2,1",
        "--strategies",
        "pwas,random",
        "--every",
        3,
        "--json",
        rows_file,
    )
    rows = json.loads(rows_file.read_text())
    assert [(r["budget"], r["strategy"]) for r in rows] == [
        (0.2, "pwas"),
        (0.2, "random"),
        (1.0, "whole map"),
    ]
    with LogReader(log) as reader:
        total = len(reader.read_map())
    for row in rows:
        assert row["gaussians"] == int(row["budget"] * total + 0.5)
        assert row["bytes_fp16"] < row["bytes_fp32"] and np.isfinite(row["psnr"])
        assert row["bytes_compact"] < row["bytes_fp16"]
        if row["budget"] < 1:
            for codec in ("fp32", "fp16", "compact"):
                dst = tmp_path / f"{row['strategy']}_{codec}.mcap"
                share = share_log(
                    log, dst, row["budget"], ShareOptions(strategy=row["strategy"], codec=codec)
                )
                assert share["bytes"] == row[f"bytes_{codec}"]


@pytest.mark.slow
def test_cluster_study_runs_each_sequence_and_tabulates_pwas_against_random(
    tiny_sequence: Path, tmp_path: Path
) -> None:
    from conftest import TINY_STUDY

    other = tmp_path / "room2"
    shutil.copytree(tiny_sequence, other)
    study = tmp_path / "study"
    options = [o for o in TINY_STUDY if o != "--json"]
    out = example(
        "cluster_study.py", tiny_sequence, other, "-o", study, "--executor", "local", "--", *options
    )
    table = json.loads((study / "summary.json").read_text())
    assert [row["sequence"] for row in table] == ["room", "room2"]
    for row in table:
        rows = json.loads((study / row["sequence"] / "results.json").read_text())
        pwas = next(r for r in rows if r["name"] == "B + pwas 0.2")
        assert row["pwas_psnr"] == pwas["psnr"] and row["runs"] == 18 and row["failed"] == 0
    assert out.splitlines()[2].startswith("| room | 0.2 |")
