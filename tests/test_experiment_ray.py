"""The experiment's runs on Ray: a two-node cluster on this machine gives the local executor's
rows; failed runs are retried once, then reported while the rest of the study completes."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from conftest import TINY_STUDY

from gscompress.errors import MissingDependencyError, OptionError
from gscompress.pipeline.experiment import ExperimentSettings, execution, run_experiment
from gscompress.pipeline.share.options import ShareOptions
from gscompress_cli.main import cli

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

TIMING = {"seconds_per_frame"}

NEEDS_A = [
    f"s0_{kind}_{end}"
    for kind in ("random_0p2", "pwas_0p2", "full")
    for end in ("share", "agent_b")
]
"""The tiny study's runs that need agent A's log (its shares and the merges of them)."""


def rows_of(folder: Path) -> list[dict]:
    """results.json's rows without their timings."""
    rows = json.loads((folder / "results.json").read_text())
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows]


@pytest.mark.filterwarnings("error:No artists with labels")  # (a plot with no run to show)
def test_two_node_ray_cluster_gives_the_local_executors_rows(
    tiny_sequence: Path, tmp_path: Path, threads_restored: None
) -> None:
    """Each run a task on one of two Ray nodes (one CPU each, so both take tasks); with one
    torch thread per task, as the local runs have, the rows are the same to the last bit."""
    pytest.importorskip("ray", reason="needs Ray: pip install 'gscompress[cluster]'")
    from ray.cluster_utils import Cluster

    node = {"num_cpus": 1, "object_store_memory": 100 * 1024**2}
    cluster = Cluster(initialize_head=True, head_node_args={**node, "include_dashboard": False})
    try:
        cluster.add_node(**node)
        ids = {n.node_id for n in cluster.list_all_nodes()}
        on_ray = tmp_path / "ray"
        args = [
            "experiment",
            str(tiny_sequence),
            "-o",
            str(on_ray),
            *TINY_STUDY,
            "--executor",
            "ray",
            "--address",
            cluster.address,
        ]
        r = CliRunner().invoke(cli, args)
        assert r.exit_code == 0, r.output
        result = json.loads(r.output)
        again = CliRunner().invoke(cli, args)  # a rerun on the cluster reuses every run
        assert again.exit_code == 0, again.output
        assert json.loads(again.output)["reused"] == result["steps"]
        # a frame that cannot be read: the runs on it fail on their node (twice), the runs
        # that need them are not run, agent B's runs complete
        broken = tmp_path / "broken"
        shutil.copytree(tiny_sequence, broken)
        (broken / "depth" / "000003.png").write_bytes(b"not a png")
        args = [
            "experiment",
            str(broken),
            "-o",
            str(tmp_path / "failing"),
            *TINY_STUDY,
            "--executor",
            "ray",
            "--address",
            cluster.address,
        ]
        failing = CliRunner().invoke(cli, args)
        # runs that no node can hold are refused, not left waiting for ever
        big = CliRunner().invoke(cli, [*args, "--cpus-per-run", "2"])
    finally:
        cluster.shutdown()
    assert result["reused"] == 0 and result["failed"] == {}
    records = [
        json.loads(p.read_text())
        for p in sorted((on_ray / "runs").glob("*.json"))
        if not p.name.endswith(".scores.json")
    ]  # (a scoring step's full results)
    assert len(records) == result["steps"] == 18  # 11 runs, 7 cross-agent scoring steps
    assert len(list((on_ray / "runs").glob("*_xeval.scores.json"))) == 7
    ran_on = {record["ran_on"]["node"] for record in records}
    assert len(ids) == 2 and ran_on == ids  # both nodes ran tasks

    assert big.exit_code == 2 and "no node of the Ray cluster has 2 CPUs" in big.output
    assert failing.exit_code == 1, failing.output
    failed = json.loads(failing.stdout)["failed"]
    scoring = [
        f"{name}_xeval"
        for name in ("full_pwas", "s0_agent_a", "s0_agent_b", "s0_no_share_agent_b", *NEEDS_A[1::2])
    ]
    assert set(failed) == {"full_no_prune", "full_pwas", "s0_agent_a", *NEEDS_A, *scoring}
    assert failed["s0_agent_a"].startswith("DatasetError: cannot read depth image")
    assert "its last log lines" in failed["s0_agent_a"]
    md = (tmp_path / "failing" / "results.md").read_text()
    assert "## Failed runs" in md and "| s0_agent_a | DatasetError: cannot read" in md
    for name in ("s0_agent_b", "s0_no_share_agent_b"):  # B's frames are even: 0 and 2
        assert (tmp_path / "failing" / "runs" / f"{name}.json").is_file()

    local = tmp_path / "local"
    args = ["--threads", "1", "experiment", str(tiny_sequence), "-o", str(local), *TINY_STUDY]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    assert rows_of(on_ray) == rows_of(local)


def test_without_ray_the_ray_executor_says_how_to_install_it(
    tiny_sequence: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # (import ray raises ImportError)
    out = tmp_path / "exp"
    with pytest.raises(MissingDependencyError, match=r"pip install 'gscompress\[cluster\]'"):
        run_experiment(tiny_sequence, out, ExperimentSettings(preset="tiny"), executor="ray")
    assert not out.exists()


@pytest.mark.parametrize(
    "options",
    [
        {"executor": "ray", "jobs": 2},
        {"address": "auto"},
        {"cpus_per_run": 2.0},
        {"executor": "slurm"},
    ],
)
def test_options_of_another_executor_are_refused(
    tiny_sequence: Path, tmp_path: Path, options: dict
) -> None:
    with pytest.raises(OptionError):
        run_experiment(
            tiny_sequence, tmp_path / "exp", ExperimentSettings(preset="tiny"), **options
        )
    assert not (tmp_path / "exp").exists()


def test_a_failing_run_is_retried_once_then_reported_and_the_rest_completes(
    tiny_sequence: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The random share fails (twice): results.md lists it and the merge that needs it, every
    other row has its figures, the command exits 1 and the failing run's log lines reach the
    user; the same command then redoes only those two runs."""
    attempts = []
    share_job = execution._share_job

    def failing(path: Path, source: Path, budget: str, options: ShareOptions, **more: Any) -> dict:
        if options.strategy == "random":
            attempts.append(path.name)
            execution.log.warning("about to fail")
            raise RuntimeError("disk on fire")
        return share_job(path, source, budget, options, **more)

    monkeypatch.setattr(execution, "_share_job", failing)
    out = tmp_path / "exp"
    args = ["experiment", str(tiny_sequence), "-o", str(out), *TINY_STUDY]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 1, r.output
    assert attempts == ["s0_random_0p2_share.mcap"] * 2
    result = json.loads(r.stdout)
    share, merge = "s0_random_0p2_share", "s0_random_0p2_agent_b"
    assert set(result["failed"]) == {share, merge, f"{merge}_xeval"}
    assert result["failed"][share].startswith("RuntimeError: disk on fire")
    assert result["failed"][merge] == f"not run: it needs {share}, which failed"
    assert "about to fail" in result["failed"][share]  # the run's own log lines
    logged = [rec.getMessage() for rec in caplog.records if rec.levelname == "ERROR"]
    assert any("disk on fire" in m and "about to fail" in m for m in logged)
    rows = json.loads((out / "results.json").read_text())
    failed = [row for row in rows if row["error"]]
    assert [row["name"] for row in failed] == ["B + random 0.2"]
    assert failed[0]["psnr"] is None and failed[0]["log"] is None
    assert all(row["psnr"] is not None for row in rows if not row["error"])
    md = (out / "results.md").read_text()
    assert "## Failed runs" in md and f"| {share} | RuntimeError: disk on fire |" in md
    assert not (out / "runs" / f"{share}.json").exists()

    monkeypatch.setattr(execution, "_share_job", share_job)
    again = CliRunner().invoke(cli, args)
    assert again.exit_code == 0, again.output
    result = json.loads(again.output)
    assert result["failed"] == {} and result["reused"] == result["steps"] - 3
    assert "## Failed runs" not in (out / "results.md").read_text()
