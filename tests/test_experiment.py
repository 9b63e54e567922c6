"""`gsc experiment` end to end on the tiny preset: tables, plots, and reuse on a rerun."""

from __future__ import annotations

import csv
import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.errors import InputError, OptionError
from gscompress.io.mcap_log import LogReader
from gscompress.pipeline.experiment import (
    ROW_KEYS,
    ExperimentSettings,
    halves,
    paired_difference,
    plan_size,
    rate_distortion_curves,
    resolve_settings,
)
from gscompress.pipeline.experiment.protocol import FULL_STUDY, PROTOCOLS, reference_formats
from gscompress.pipeline.experiment.results import curve_at
from gscompress.pipeline.share.cut import smallest_share_bytes
from gscompress_cli.main import cli

# runs SLAM (or another minutes-long pipeline): not in `make test-fast`
pytestmark = pytest.mark.slow

REQUIRED = ("name", "ate_rmse_cm", "psnr", "ssim", "lpips", "gaussians", "bytes")

REFINE = ("--refine-poses", "3")
"""The fixture's cross-agent scoring: 3 tracking iterations per frame (seconds, not minutes)."""

CROSS = ("refined_psnr_a", "refined_psnr_b", "refined_psnr_all")

STUDY = ("--full", "--protocol", "paper")
"""The fixture's study: the whole one (five strategies, the sweep), the paper's protocol."""

PAPER_FULL = {**FULL_STUDY, **PROTOCOLS["paper"]}
"""`ExperimentSettings` of `STUDY` (but the seeds and scoring iterations the tests give)."""


def _args(seq: Path, out: Path, *extra: str, refine: tuple[str, ...] = REFINE) -> list[str]:
    """The command line of the fixture's experiment written to `out`, with `extra` options."""
    return [
        "experiment",
        str(seq),
        "-o",
        str(out),
        "--preset",
        "tiny",
        "--seeds",
        "1",
        "--sweep",
        "0.2,0.5",
        "--no-lpips",
        "--json",
        *STUDY,
        *refine,
        *extra,
    ]


def _run(seq: Path, out: Path, *extra: str, refine: tuple[str, ...] = REFINE) -> dict:
    """The fixture's experiment written to `out`, with `extra` options; its JSON result."""
    r = CliRunner().invoke(cli, _args(seq, out, *extra, refine=refine))
    assert r.exit_code == 0, r.output
    return json.loads(r.output)


def _copy(experiment: tuple[Path, Path, dict], tmp_path: Path) -> Path:
    """A copy of the fixture's folder for a test that reruns it otherwise (the folder itself is
    shared by the tests of this module)."""
    copy = tmp_path / "copy"
    shutil.copytree(experiment[1], copy)
    return copy


@pytest.fixture(scope="module")
def experiment(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict]:
    root = tmp_path_factory.mktemp("exp")
    seq = write_synthetic_sequence(root / "room", 4, (64, 48))
    out = root / "exp"
    return seq, out, _run(seq, out)


def test_experiment_writes_tables_rows_and_plots(experiment: tuple[Path, Path, dict]) -> None:
    _seq, out, result = experiment
    settings = ExperimentSettings(
        **{
            **PAPER_FULL,
            "preset": "tiny",
            "seeds": 1,
            "sweep": ("0.2", "0.5"),
            "lpips": False,
            "refine_poses": 3,
        }
    )
    assert result["steps"] == plan_size(settings) and result["reused"] == 0
    rows = json.loads((out / "results.json").read_text())
    assert all(set(REQUIRED) <= set(row) for row in rows)
    tables = [row["table"] for row in rows]
    assert tables.count("table3") == 2
    # A, B, B refined without a share, five strategies, the full map
    assert tables.count("table4") == 2 + 1 + 5 + 1
    assert tables.count("sweep") == 5  # five strategies at 0.5 (0.2 is Table 4's)
    for row in rows:
        with LogReader(out / row["log"]) as log:
            assert log.read_map().__len__() == row["gaussians"]
    by_name = {(r["name"], r["table"]): r for r in rows}
    pwas, full = by_name[("B + pwas 0.2", "table4")], by_name[("B + A's full map", "table4")]
    a, b = by_name[("agent A (odd frames)", "table4")], by_name[("agent B (even frames)", "table4")]
    alone = by_name[("B refined, no share", "table4")]
    assert alone["gaussians"] == b["gaussians"] and alone["share_gaussians"] is None
    assert pwas["gaussians"] == b["gaussians"] + pwas["share_gaussians"]  # a merge drops none
    assert pwas["share_gaussians"] == round(0.2 * a["gaussians"])
    assert full["share_gaussians"] == a["gaussians"] and full["share_bytes"] > pwas["share_bytes"]
    # A's whole map in the field's formats, each received like a share (SOG where it can be
    # written: CI installs splat-transform)
    formats = reference_formats(settings)
    assert {"fp32", "spz"} <= set(formats)
    whole = {r["strategy"]: r for r in rows if r["table"] == "reference"}
    assert set(whole) == set(formats)
    for fmt, row in whole.items():
        assert row["name"] == f"B + A's whole map as {fmt}" and not row["error"]
        assert row["share_gaussians"] == a["gaussians"]
        assert row["gaussians"] == b["gaussians"] + a["gaussians"]  # (the exact merge)
        assert row["refined_psnr_all"] is not None
    assert whole["spz"]["share_bytes"] < full["share_bytes"] < whole["fp32"]["share_bytes"]
    with open(out / "results.csv", newline="") as f:
        assert set(next(iter(csv.DictReader(f)))) == set(ROW_KEYS)
    md = (out / "results.md").read_text()
    assert "## Table 3" in md and "## Table 4" in md and "Rate-distortion" in md
    assert "Preset `tiny`, keep 0.3, budget 0.2" in md  # as resolved from the preset
    assert result["verdicts"]["mode"] == "merge"
    for name in ("rate_distortion", "importance_hist", "importance_topdown"):
        assert (out / "plots" / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        with Image.open(out / "plots" / f"{name}.png") as png:
            assert round(png.info["dpi"][0]) == 200
        svg = (out / "plots" / f"{name}.svg").read_text()
        assert "<svg" in svg and f"{_seq.name}, split odd-even" in svg  # the title says which
    assert "shows PSNR alone: a merge leaves B's poses as they were" in md
    assert result["verdicts"]["seeds"] == 1 and len(result["verdicts"]["sweep"]) == 2
    first = result["verdicts"]["sweep"][0]  # one seed: a difference, no standard error
    # ranked on all frames at refined poses (B's own frames barely see what a share brings)
    assert result["verdicts"]["psnr_key"] == "refined_psnr_all"
    pwas, random = (
        by_name[(f"B + {k} 0.2", "table4")]["refined_psnr_all"] for k in ("pwas", "random")
    )
    assert first["pairs"] == 1 and first["psnr_difference_se"] is None
    assert first["psnr_difference"] == pytest.approx(pwas - random)
    cells = result["verdicts"]["cells"]  # 1 seed x 2 budgets, PWAS against three others
    against_all = {"random", "opacity", "alpha-t", "pwas-inf"}  # (and its ablation, paired)
    assert cells["cells"] == 2 and set(cells["against"]) == against_all
    against = cells["against"]["random"]
    assert against["above"] + against["ties"] + against["below"] == against["pairs"] == 2

    def psnr(strategy: str, budget: str, table: str) -> float:
        return by_name[(f"B + {strategy} {budget}", table)]["refined_psnr_all"]

    margins = [
        min(psnr("pwas", b, t) - psnr(o, b, t) for o in ("random", "opacity", "alpha-t"))
        for b, t in (("0.2", "table4"), ("0.5", "sweep"))
    ]
    assert cells["at_or_above"] == sum(m >= -0.005 for m in margins)
    assert f"weight) in {cells['at_or_above']} of 2 cells" in md
    assert "PWAS minus random, paired by seed" in md and "ATE RMSE (cm) | PWAS lower" not in md
    assert "| A's whole map as | Gaussians | Bytes |" in md
    for fmt in formats:
        assert f"| {fmt} | {a['gaussians']} | {whole[fmt]['share_bytes']} |" in md


def test_pwas_without_proximity_ranks_a_scored_again_from_its_own_frames(
    experiment: tuple[Path, Path, dict],
) -> None:
    """The ablation pwas-inf: A's finished map scored again from A's frames at A's poses with no
    proximity weight (every visible frame weighs 1, so W counts the frames and S is the alpha*T
    sum), and its shares cut by that PWAS; pwas-final (the scene's sigma_d) runs when asked."""
    _seq, out, _result = experiment
    runs = out / "runs"
    with LogReader(runs / "s0_agent_a.mcap") as log:
        online = log.read_map()
    with LogReader(runs / "s0_agent_a_pwas-inf.mcap") as log:
        scored, meta = log.read_map(), log.metadata
    assert meta.results["sigma_d"] == "inf" and meta.results["views"] == 2  # A's odd frames of 4
    np.testing.assert_array_equal(scored.means, online.means)
    np.testing.assert_allclose(scored.importance_sum, scored.alpha_t_sum, rtol=1e-6)
    assert set(np.unique(scored.importance_weight)) <= {0.0, 1.0, 2.0}
    assert not np.allclose(scored.importance, online.importance)  # (the weight did something)
    with LogReader(runs / "s0_pwas-inf_0p2_share.mcap") as log:
        share = log.metadata.results
    assert (share["source"], share["strategy"]) == ("s0_agent_a_pwas-inf.mcap", "pwas")
    assert share["selected"] == round(0.2 * len(online))
    rows = json.loads((out / "results.json").read_text())
    assert {r["name"] for r in rows if r["strategy"] == "pwas-inf"} == {
        "B + pwas-inf 0.2",
        "B + pwas-inf 0.5",
    }
    settings = ExperimentSettings(strategies=("random", "pwas", "pwas-final"))
    settings.check()
    with pytest.raises(OptionError, match="unknown strategies"):
        ExperimentSettings(strategies=("random", "pwas", "pwas-zero")).check()


def test_cross_agent_scoring_fills_the_three_columns(experiment: tuple[Path, Path, dict]) -> None:
    """The centralised run, A, B and every run of B are scored on A's, B's and all frames at
    refined poses; each B map starts at B's poses on B's frames, at A's on A's, and on all
    frames at its own where it has them and A's elsewhere."""
    from gscompress.io.trajectory import read_tum_trajectory
    from gscompress.pipeline.logs import pose_source

    _seq, out, _result = experiment
    rows = json.loads((out / "results.json").read_text())
    scored = [r for r in rows if r["refine_iters"] is not None]
    assert [r["name"] for r in rows if r not in scored] == ["full, no pruning"]
    references = len(reference_formats(ExperimentSettings()))  # (B with A's whole map in each)
    assert len(scored) == 15 + references and all(r["refine_iters"] == 3 for r in scored)
    for row in scored:
        for name in ("a", "b", "all"):
            assert math.isfinite(row[f"refined_psnr_{name}"]), row
            assert math.isfinite(row[f"start_psnr_{name}"]), row
            assert 0 <= row[f"pose_change_cm_{name}"] < 50, row
    record = json.loads((out / "runs" / "s0_pwas_0p2_agent_b_xeval.json").read_text())
    cross = record["result"]["cross"]
    assert [cross[k]["start"] for k in ("a", "b", "all")] == [
        "the other agent's",
        "own",
        "own, the other agent's elsewhere",
    ]
    assert (cross["a"]["frames"], cross["b"]["frames"]) == ("odd", "even")
    assert cross["all"]["frames_evaluated"] == 4 and cross["a"]["frames_evaluated"] == 2
    centralised = json.loads((out / "runs" / "full_pwas_xeval.json").read_text())["result"]
    assert {v["start"] for v in centralised["cross"].values()} == {"own"}
    # on all frames: B's own poses on the even frames, A's on the odd ones
    start = read_tum_trajectory(out / "runs" / "s0_pwas_0p2_agent_b_xeval_start_all.txt")
    poses_a = pose_source(out / "runs" / "s0_agent_a.mcap").T_world_cam
    poses_b = pose_source(out / "runs" / "s0_pwas_0p2_agent_b.mcap").T_world_cam
    np.testing.assert_allclose(start.T_world_cam[0::2], poses_b, atol=1e-12)
    np.testing.assert_allclose(start.T_world_cam[1::2], poses_a, atol=1e-12)
    with open(out / "results.csv", newline="") as f:
        assert set(CROSS) <= set(next(iter(csv.DictReader(f))))
    md = (out / "results.md").read_text()
    title = "## PSNR on A's frames / B's frames / all frames, poses refined (3 iterations)"
    assert title in md
    table = md.split(title)[1].split("\n## ")[0]
    assert "| centralised (full, PWAS pruning) |" in table and "| B + A's full map |" in table
    references = len(reference_formats(ExperimentSettings()))
    assert table.count(" cm) |\n") == 15 + references and "n/a" not in table


def test_refine_poses_0_leaves_the_own_frame_scores_alone(
    experiment: tuple[Path, Path, dict], tmp_path: Path
) -> None:
    """--refine-poses 0: no scoring step, and the rows and results.md are those of the same
    experiment with cross-agent scoring, less its columns (empty) and its table."""
    seq, copy = experiment[0], _copy(experiment, tmp_path)
    _run(seq, copy)  # (the fixture's reports, rewritten)
    scored = json.loads((copy / "results.json").read_text())
    scored_md = (copy / "results.md").read_text()
    result = _run(seq, copy, refine=("--refine-poses", "0"))
    settings = ExperimentSettings(
        **{**PAPER_FULL, "preset": "tiny", "seeds": 1, "sweep": ("0.2", "0.5"), "refine_poses": 0}
    )
    references = len(reference_formats(settings))  # (a share and B's run with it, each)
    assert result["steps"] == result["reused"] == plan_size(settings) == 28 + 2 * references
    rows = json.loads((copy / "results.json").read_text())
    cross = {k for k in ROW_KEYS if k.endswith(("_a", "_b", "_all")) or k == "refine_iters"}
    assert len(cross) == 13
    assert all(row[k] is None for row in rows for k in cross)
    assert rows == [{k: (None if k in cross else v) for k, v in row.items()} for row in scored]
    md = (copy / "results.md").read_text()
    assert "poses refined" not in md and "## PSNR on A's frames" not in md
    verdict = "PWAS beats random at"
    assert md[: md.index(verdict)] == scored_md[: scored_md.index(verdict)]  # Tables 3 and 4
    # the shares are ranked on B's own frames, all frames needing refined poses
    assert "on PSNR (B's own frames at B's estimated poses)" in md
    assert "on PSNR (all frames, each pose refined" in scored_md


def test_parallel_runs_give_the_same_rows(
    experiment: tuple[Path, Path, dict], threads_restored: None
) -> None:
    """--jobs 2: the steps run in two worker processes, each as soon as the logs it reads
    exist, and the rows are those of the runs made one after another with as many threads."""
    import torch

    seq, out, first = experiment
    parallel = out.parent / "parallel"
    threads = 2 * torch.get_num_threads()  # each worker gets what the fixture's runs had
    args = ["--threads", str(threads), *_args(seq, parallel, "--jobs", "2")]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    assert result["steps"] == first["steps"] and result["reused"] == 0
    ours, theirs = (json.loads((d / "results.json").read_text()) for d in (parallel, out))
    timing = {"seconds_per_frame"}
    assert [{k: v for k, v in row.items() if k not in timing} for row in ours] == [
        {k: v for k, v in row.items() if k not in timing} for row in theirs
    ]
    again = CliRunner().invoke(cli, args)  # a rerun reuses them all, in parallel mode too
    assert again.exit_code == 0 and json.loads(again.output)["reused"] == first["steps"]


def test_rate_distortion_curves_start_at_b_without_a_share(
    experiment: tuple[Path, Path, dict],
) -> None:
    _seq, out, _result = experiment
    settings = ExperimentSettings(
        **{**PAPER_FULL, "preset": "tiny", "seeds": 1, "sweep": ("0.2", "0.5"), "lpips": False}
    )
    rows = json.loads((out / "results.json").read_text())
    alone = next(r for r in rows if r["name"] == "B refined, no share")
    full = next(r for r in rows if r["strategy"] == "full")
    # PSNR on all frames at refined poses; with --refine-poses 0, B's own frames
    for refine, key in ((100, "refined_psnr_all"), (0, "psnr")):
        curves = rate_distortion_curves(rows, replace(settings, refine_poses=refine))
        formats = reference_formats(settings)
        strategies = ("random", "opacity", "alpha-t", "pwas", "pwas-inf")
        assert set(curves) == {*strategies, "full", *formats}
        for fmt in formats:
            whole = next(r for r in rows if r["table"] == "reference" and r["strategy"] == fmt)
            assert curves[fmt] == [(whole["share_bytes"], whole[key], whole["ate_rmse_cm"])]
        for strategy in strategies:
            (x0, psnr0, ate0), *shared = curves[strategy]
            assert (x0, psnr0, ate0) == (0.0, alone[key], alone["ate_rmse_cm"])
            sweep = [r for r in rows if r["strategy"] == strategy]
            assert [p[0] for p in shared] == sorted(r["share_bytes"] for r in sweep)
            assert [p[1] for p in shared] == [
                r[key] for r in sorted(sweep, key=lambda r: r["share_bytes"])
            ]
        assert curves["full"] == [(full["share_bytes"], full[key], full["ate_rmse_cm"])]
    inject = ExperimentSettings(
        **{**PAPER_FULL, "preset": "tiny", "seeds": 1, "sweep": ("0.2", "0.5"), "mode": "inject"}
    )
    b = next(r for r in rows if r["name"] == "agent B (even frames)")
    assert rate_distortion_curves(rows, inject)["pwas"][0][1] == b["refined_psnr_all"]
    assert rate_distortion_curves(rows, ExperimentSettings(preset="tiny", sweep_seeds=0)) == {}


def test_a_curve_is_read_between_its_shares_on_log_bytes() -> None:
    points = [(0.0, 10.0, None), (100.0, 20.0, None), (10000.0, 30.0, None)]
    assert curve_at(points, 1000.0) == pytest.approx(25.0)  # halfway on a log axis
    assert curve_at(points, 100.0) == 20.0 and curve_at(points, 10000.0) == 30.0
    assert curve_at(points, 50.0) is None  # below the first share (0 bytes is not a share)
    assert curve_at(points, 20000.0) is None and curve_at([], 5.0) is None


def test_unknown_reference_formats_are_refused() -> None:
    r = CliRunner().invoke(cli, ["experiment", ".", "-o", "x", "--references", "fp32,ply"])
    assert r.exit_code == 2 and "unknown format 'ply'" in r.output, r.output
    with pytest.raises(OptionError, match="unknown reference formats"):
        ExperimentSettings(references=("zip",)).check()
    assert ExperimentSettings(references=()).references == ()


def test_pwas_minus_random_is_paired_by_seed() -> None:
    def row(seed: int, strategy: str, psnr: float | None) -> dict:
        return {"seed": seed, "budget": "0.2", "strategy": strategy, "psnr": psnr}

    group = [
        row(0, "pwas", 25.0),
        row(0, "random", 24.9),
        row(1, "random", 25.3),
        row(1, "pwas", 25.2),
        row(2, "pwas", 24.9),
        row(2, "random", 24.6),
        row(2, "opacity", 30.0),  # another strategy: not compared
        row(3, "pwas", 26.0),  # no random run for seed 3
        row(4, "pwas", None),
        row(4, "random", 24.0),  # no PSNR for PWAS
        row(5, "pwas", float("nan")),
        row(5, "random", 24.0),
    ]
    d = paired_difference(group, "psnr")  # differences +0.1, -0.1, +0.3
    assert (d["pairs"], d["positive"], d["negative"]) == (3, 2, 1)
    assert (d["above"], d["ties"], d["below"]) == (2, 0, 1)
    assert d["mean"] == pytest.approx(0.1)
    assert d["se"] == pytest.approx(0.2 / 3**0.5)
    none = paired_difference(group[6:8], "psnr")
    assert none == {
        "pairs": 0,
        "mean": None,
        "se": None,
        "positive": 0,
        "negative": 0,
        "above": 0,
        "below": 0,
        "ties": 0,
    }
    opacity = paired_difference(group, "psnr", "opacity")  # seed 2 only: 24.9 - 30.0
    assert opacity["pairs"] == 1 and opacity["mean"] == pytest.approx(-5.1)
    # pairs are (seed, budget) cells; a difference within TIE_DB is a tie, counted apart
    cells = [
        {"seed": 0, "budget": b, "strategy": k, "psnr": v}
        for b, k, v in [
            ("1%", "pwas", 20.0),
            ("1%", "random", 20.004),
            ("2%", "pwas", 21.0),
            ("2%", "random", 20.5),
        ]
    ]
    tied = paired_difference(cells, "psnr")
    assert (tied["pairs"], tied["above"], tied["ties"], tied["below"]) == (2, 1, 1, 0)


def test_rerun_reuses_finished_runs_and_redoes_only_what_changed(
    experiment: tuple[Path, Path, dict], tmp_path: Path
) -> None:
    seq, out, first = experiment
    scoring = sorted((out / "runs").glob("*_xeval.json"))
    references = len(reference_formats(ExperimentSettings()))
    assert len(scoring) == 15 + references  # all the rows but Table 3's unpruned run
    before = {p.name: p.read_bytes() for p in scoring}
    again = _run(seq, out)
    assert again["reused"] == again["steps"] == first["steps"]  # the scoring steps too
    assert {p.name: p.read_bytes() for p in scoring} == before
    # a new sweep budget: only its shares, B runs and their scoring are new (5 strategies x 3)
    third = _run(seq, out, "--sweep", "0.2,0.5,0.3")  # (the last --sweep counts)
    assert third["steps"] - third["reused"] == 15
    # another merge learning-rate decay: every merge again, nothing else (in a copy: the
    # folder is shared with the other tests of this module)
    copy = _copy(experiment, tmp_path)
    fourth = _run(seq, copy, "--sweep", "0.2,0.5,0.3", "--merge-lr-final", "0.5")
    merges = list((copy / "runs").glob("s0_*_agent_b.json"))  # not B's own run, s0_agent_b
    # 5 strategies x 3 + 2 + A's whole map in each reference format, each scored again
    assert len(merges) == 17 + references
    assert fourth["steps"] - fourth["reused"] == 2 * len(merges)
    assert all(json.loads(p.read_text())["spec"]["lr_final"] == 0.5 for p in merges)


def test_a_damaged_run_record_is_a_run_to_do_again(
    experiment: tuple[Path, Path, dict], tmp_path: Path
) -> None:
    seq, copy = experiment[0], _copy(experiment, tmp_path)
    damaged = {"full_pwas": b"\xff\xfe not text", "full_no_prune": b"[]"}
    for name, data in damaged.items():
        (copy / "runs" / f"{name}.json").write_bytes(data)
    record_path = copy / "runs" / "s0_agent_a.json"  # its key intact, its result not
    record = json.loads(record_path.read_text())
    record["result"]["eval"] = {}
    record_path.write_text(json.dumps(record))
    damaged["s0_agent_a"] = b""
    again = _run(seq, copy)
    assert again["steps"] - again["reused"] == len(damaged)  # those three, nothing else
    for name in damaged:
        assert json.loads((copy / "runs" / f"{name}.json").read_text())["result"]


def test_bad_settings_are_refused() -> None:
    with pytest.raises(InputError, match="random and pwas"):
        ExperimentSettings(strategies=("opacity",)).check()
    smallest = smallest_share_bytes()  # a compact share file of one Gaussian
    with pytest.raises(
        InputError, match=rf"budget of {smallest - 1}B cannot hold one Gaussian.* {smallest} B"
    ):
        ExperimentSettings(sweep=("0.2", f"{smallest - 1}B")).check()
    ExperimentSettings(budget=f"{smallest}B").check()  # one Gaussian may fit
    r = CliRunner().invoke(cli, ["experiment", ".", "-o", "x", "--sweep", "2"])
    assert r.exit_code == 2 and "unit" in r.output
    for bad in (["--frames", "odd"], ["--strategies", "random,pwas,nope"]):  # usage errors
        r = CliRunner().invoke(cli, ["experiment", ".", "-o", "x", *bad])
        assert r.exit_code == 2 and "Error:" in r.output, r.output
    r = CliRunner().invoke(
        cli, ["experiment", ".", "-o", "x", "--seeds", "1", "--sweep-seeds", "3"]
    )
    assert r.exit_code == 2 and "--sweep-seeds 3 is more than --seeds 1" in r.output, r.output


def test_a_bad_sequence_fails_before_the_output_folder_is_made(tmp_path: Path) -> None:
    (tmp_path / "notes").mkdir()
    r = CliRunner().invoke(cli, ["experiment", str(tmp_path / "notes"), "-o", str(tmp_path / "e")])
    assert r.exit_code == 1 and "not a known RGB-D layout" in r.output
    assert not (tmp_path / "e").exists()


def test_frames_that_leave_an_agent_nothing_or_a_folder_in_the_sequence_fail_at_once(
    experiment: tuple[Path, Path, dict], tmp_path: Path
) -> None:
    seq, _, _ = experiment
    r = CliRunner().invoke(
        cli, ["experiment", str(seq), "-o", str(tmp_path / "e"), "--frames", "0:1"]
    )
    assert r.exit_code == 1 and "leaves agent A (1:1:2) no frame" in r.output, r.output
    r = CliRunner().invoke(cli, ["experiment", str(seq), "-o", str(seq / "e")])
    assert r.exit_code == 1 and "inside the sequence folder" in r.output, r.output
    for option in ("--jobs", "--seeds"):  # huge counts: a usage error, not an overflow
        r = CliRunner().invoke(
            cli, ["experiment", str(seq), "-o", str(tmp_path / "e"), option, str(10**22)]
        )
        assert r.exit_code == 2 and "is not in the range 1<=x<=" in r.output, r.output
    assert not (tmp_path / "e").exists() and not (seq / "e").exists()
    r = CliRunner().invoke(
        cli, ["experiment", str(seq), "-o", str(tmp_path / "e"), "--frames", "x"]
    )
    assert r.exit_code == 2 and "takes all or START:STOP:STEP" in r.output, r.output


def test_a_folder_of_other_files_is_not_written_into(
    experiment: tuple[Path, Path, dict], tmp_path: Path
) -> None:
    seq, _, _ = experiment
    (tmp_path / "results.md").write_text("mine")
    (tmp_path / "notes.txt").write_text("mine")
    r = CliRunner().invoke(cli, ["experiment", str(seq), "-o", str(tmp_path), "--preset", "tiny"])
    assert r.exit_code == 1 and "not an experiment's (notes.txt)" in r.output, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "results.md"]
    assert (tmp_path / "results.md").read_text() == "mine"


def test_budgets_written_differently_are_thesame_budget() -> None:
    from gscompress.pipeline.experiment.protocol import same_budget

    assert same_budget("0.2", "20%") and same_budget("2MB", "2000kB")
    assert not same_budget("0.2", "0.3") and not same_budget("0.2", "")
    assert same_budget("5%bytes", "5.0%bytes") and not same_budget("2%bytes", "5%bytes")
    assert not same_budget("5%bytes", "5%")  # of the bytes, not of the Gaussians
    # the main budget written as a percentage is not run twice in the sweep
    settings = ExperimentSettings(budget="20%", sweep=("0.2", "0.4"), seeds=1)
    assert plan_size(settings) == plan_size(ExperimentSettings(sweep=("0.4",), seeds=1))


def test_agent_frames_split_the_experiment_frames() -> None:
    from gscompress.datasets.base import parse_frames

    assert ExperimentSettings().agent_frames() == ("odd", "even")
    a, b = ExperimentSettings(frames="10:30").agent_frames()
    assert list(parse_frames(a).apply(100)) == list(range(11, 30, 2))
    assert list(parse_frames(b).apply(100)) == list(range(10, 30, 2))
    a, b = ExperimentSettings(frames="::3").agent_frames()
    assert list(parse_frames(a).apply(20)) == [3, 9, 15] and list(parse_frames(b).apply(20)) == [
        0,
        6,
        12,
        18,
    ]
    with pytest.raises(InputError):
        ExperimentSettings(frames="odd").check()


def test_inject_mode_runs_b_again_with_the_share(experiment: tuple[Path, Path, dict]) -> None:
    seq, out, _ = experiment
    inject = out.parent / "inject"
    args = [
        "experiment",
        str(seq),
        "-o",
        str(inject),
        "--preset",
        "tiny",
        "--seeds",
        "1",
        "--sweep",
        "0.2",
        "--strategies",
        "random,pwas",
        "--mode",
        "inject",
        "--sweep-seeds",
        "0",
        "--no-lpips",
        "--json",
        "--refine-poses",
        "0",
    ]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    rows = json.loads((inject / "results.json").read_text())
    pwas = next(r for r in rows if r["name"] == "B + pwas 0.2")
    with LogReader(inject / pwas["log"]) as log:
        step = log.metadata.provenance[-1]
        frames = log.metadata.results["frames"]
    assert step["operation"]["name"] == "inject" and frames == 2  # a new SLAM run of B
    # without a sweep there is no rate-distortion table or plot, and results.md says so
    assert "No sweep was run" in (inject / "results.md").read_text()
    assert not (inject / "plots" / "rate_distortion.png").exists()


def test_both_modes_share_one_folder_without_overwriting_runs(
    experiment: tuple[Path, Path, dict],
) -> None:
    seq, out, first = experiment
    base = _args(seq, out)
    r = CliRunner().invoke(cli, [*base, "--mode", "inject", "--strategies", "random,pwas"])
    assert r.exit_code == 0, r.output
    inject = json.loads(r.output)
    # A, B, the shares and their scoring are reused; only B's runs with a share (2 x 2
    # budgets + full, and A's whole map in each reference format) and their scoring are new
    assert inject["steps"] - inject["reused"] == 2 * (
        5 + len(reference_formats(ExperimentSettings()))
    )
    assert "ATE RMSE (cm) | PWAS lower" in (out / "results.md").read_text()  # B's poses move
    r = CliRunner().invoke(cli, base)  # back to merge mode: every merge run is still there
    assert r.exit_code == 0, r.output
    again = json.loads(r.output)
    assert again["reused"] == again["steps"] == first["steps"]


def _children(pid: int) -> set[int]:
    """The live child processes of `pid` (from /proc; zombies left out)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            state, ppid = stat.read_text().rsplit(")", 1)[1].split()[:2]
        except (OSError, IndexError, ValueError):
            continue  # ended meanwhile
        if int(ppid) == pid and state != "Z":
            found.add(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="reads /proc (Linux)")
def test_sigterm_stops_the_workers_and_a_rerun_goes_on(tmp_path: Path) -> None:
    """SIGTERM (or Ctrl-C) to `gsc experiment --jobs 2` while runs are under way: the command
    ends with 130 and says how to go on, no worker outlives it, the runs it finished keep their
    records, and the same command reuses them."""
    import signal
    import subprocess
    import sys
    import time

    seq = write_synthetic_sequence(tmp_path / "room", 16, (64, 48))
    out = tmp_path / "exp"
    args = [
        "experiment",
        str(seq),
        "-o",
        str(out),
        "--preset",
        "tiny",
        "--seeds",
        "1",
        "--sweep-seeds",
        "0",
        "--no-lpips",
        "--json",
        "--refine-poses",
        "0",
    ]
    cmd = [sys.executable, "-m", "gscompress_cli", "--threads", "2", *args, "--jobs", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300
        while not list((out / "runs").glob("*.json")):  # the first run has finished
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.1)
        workers = _children(proc.pid)
        assert workers  # the pool's workers (and the resource tracker)
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert b"Interrupted" in stderr and b"reuses them" in stderr
    time.sleep(1.0)  # an orphan is reaped by its new parent
    assert not [pid for pid in workers if _alive(pid)]
    records = sorted(p.stem for p in (out / "runs").glob("*.json"))
    total = plan_size(
        ExperimentSettings(preset="tiny", seeds=1, sweep_seeds=0, lpips=False, refine_poses=0)
    )
    assert 0 < len(records) < total  # stopped part-way, nothing recorded for the runs it cut
    for name in records:
        with LogReader(out / "runs" / f"{name}.mcap") as log:
            assert len(log.read_map()) > 0
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    result = json.loads(r.output)
    assert result["steps"] == total and result["reused"] >= len(records)


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="reads /proc (Linux)")
def test_workers_end_when_the_runner_is_killed_outright(tmp_path: Path) -> None:
    """SIGKILL to `gsc experiment --jobs 2` (no handler can run): its worker processes, idle
    or in a run, end too instead of waiting for work from a runner that is gone."""
    import os
    import signal
    import subprocess
    import sys
    import time

    seq = write_synthetic_sequence(tmp_path / "room", 16, (64, 48))
    out = tmp_path / "exp"
    cmd = [
        sys.executable,
        "-m",
        "gscompress_cli",
        "--threads",
        "2",
        "experiment",
        str(seq),
        "-o",
        str(out),
        "--preset",
        "tiny",
        "--seeds",
        "1",
        "--sweep-seeds",
        "0",
        "--no-lpips",
        "--jobs",
        "2",
        "--refine-poses",
        "0",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300
        while not list((out / "runs").glob("*.json")):  # the workers are up and running
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.1)
        workers = _children(proc.pid)  # the pool's workers and the resource tracker
        assert any(b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes() for pid in workers)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        proc.kill()
    deadline = time.monotonic() + 60  # a worker in a render step ends at its next bytecode
    while [pid for pid in workers if _alive(pid)] and time.monotonic() < deadline:
        time.sleep(0.2)
    left = [pid for pid in workers if _alive(pid)]
    for pid in left:  # not to leave them behind when the test fails
        os.kill(pid, signal.SIGKILL)
    assert not left


def test_the_config_file_sets_preset_and_keep_unless_options_do(tmp_path: Path) -> None:
    """As for `gsc slam`: --keep and --preset default to the config file's, not to fixed
    values that would override it."""
    cfg = tmp_path / "k.yaml"
    cfg.write_text("preset: tiny\nprune:\n  keep: 0.5\n")
    s, base = resolve_settings(ExperimentSettings(config_path=str(cfg)))
    assert (s.preset, s.keep, base.prune.keep, base.mapping.iters) == ("tiny", 0.5, 0.5, 6)
    s, base = resolve_settings(ExperimentSettings(config_path=str(cfg), keep=0.4))
    assert (s.keep, base.prune.keep) == (0.4, 0.4)
    s, _ = resolve_settings(ExperimentSettings())
    assert (s.preset, s.keep) == ("cpu", 0.3)


def test_a_config_of_own_anchored_agents_needs_anchor_own(tmp_path: Path) -> None:
    """Agents that start at their own first frames share no frame: merged as if anchored at the
    ground truth, every cross-agent figure would be wrong."""
    cfg = tmp_path / "own.yaml"
    cfg.write_text("init_from_ground_truth: false\n")
    with pytest.raises(OptionError, match="use `anchor` own"):
        resolve_settings(ExperimentSettings(config_path=str(cfg)))
    _, base = resolve_settings(ExperimentSettings(config_path=str(cfg), anchor="own"))
    assert not base.init_from_ground_truth


def test_a_rerun_removes_what_killed_workers_left_half_written(tmp_path: Path) -> None:
    from gscompress.io.files import AtomicFile
    from gscompress.pipeline.experiment.execution import LocalRunner

    runs = tmp_path / "exp" / "runs"
    runs.mkdir(parents=True)
    left = runs / ".s0_agent_a.mcap.99999.tmp"  # a worker killed with its runner
    left.write_bytes(b"x")
    live = AtomicFile(runs / "s0_agent_b.mcap")  # another runner's worker still writing
    try:
        LocalRunner(tmp_path / "seq", tmp_path / "exp", ExperimentSettings(), None, total=1)
        assert not left.exists() and live.tmp_path.exists()
    finally:
        live.discard()


@pytest.mark.parametrize(
    "n, overlap, a_stop, b_start",
    [
        (50, 0.2, 30, 20),
        (40, 0.2, 24, 16),
        (10, 0.0, 5, 5),
        (11, 0.0, 6, 5),
        (7, 0.5, 6, 1),
        (2, 0.2, 2, 0),
        (100, 0.25, 63, 37),
    ],
)
def test_halves_gives_a_the_first_part_and_b_the_last_overlapping(n, overlap, a_stop, b_start):
    a, b = halves(n, overlap)
    assert (a.start, a.stop, b.start, b.stop) == (0, a_stop, b_start, n)
    assert len(a) == len(b) == math.ceil(n * (1 + overlap) / 2 - 1e-9)
    shared = len(set(a) & set(b))
    assert set(a) | set(b) == set(range(n)) and overlap * n <= shared <= overlap * n + 2


def test_halves_split_names_frame_subsets_of_the_experiment_frames() -> None:
    from gscompress.datasets.base import parse_frames

    settings = ExperimentSettings(split="halves", overlap=0.2)
    a, b = settings.agent_frames(50)
    assert (a, b) == ("0:30:1", "20:50:1")
    # within a subset of the sequence: positions among its frames, mapped back to indices
    a, b = ExperimentSettings(split="halves", overlap=0.2, frames="10:60:2").agent_frames(25)
    assert list(parse_frames(a).apply(100)) == list(range(10, 40, 2))  # positions 0..14
    assert list(parse_frames(b).apply(100)) == list(range(30, 60, 2))  # positions 10..24
    for bad in (
        {"split": "thirds"},
        {"split": "halves", "overlap": 1.0},
        {"split": "halves", "overlap": -0.1},
    ):
        with pytest.raises(OptionError):
            ExperimentSettings(**bad).check()
    r = CliRunner().invoke(
        cli, ["experiment", ".", "-o", "x", "--split", "halves", "--overlap", "1"]
    )
    assert r.exit_code == 2 and "--overlap" in r.output


@pytest.mark.slow
def test_anchor_own_aligns_the_agents_and_merges_at_both_transforms(tmp_path: Path) -> None:
    pytest.importorskip("open3d", reason="--anchor own needs Open3D: pip install '.[align]'")
    from gscompress.io.mcap_log import TOPIC_POSE_GT
    from gscompress.io.trajectory import read_transform

    seq = write_synthetic_sequence(tmp_path / "room", 4, (64, 48))
    out = tmp_path / "exp"
    args = [
        "experiment",
        str(seq),
        "-o",
        str(out),
        "--preset",
        "tiny",
        "--seeds",
        "1",
        "--sweep",
        "0.2",
        "--strategies",
        "random,pwas",
        "--sweep-seeds",
        "0",
        "--split",
        "halves",
        "--anchor",
        "own",
        "--merge-iters",
        "0",
        "--no-lpips",
        "--json",
        "--refine-poses",
        "2",
    ]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    settings = ExperimentSettings(
        preset="tiny",
        seeds=1,
        sweep=("0.2",),
        sweep_seeds=0,
        strategies=("random", "pwas"),
        split="halves",
        anchor="own",
        merge_iters=0,
        lpips=False,
        refine_poses=2,
    )
    assert json.loads(r.output)["steps"] == plan_size(settings)
    rows = {row["name"]: row for row in json.loads((out / "results.json").read_text())}
    est, true = rows["B + pwas 0.2"], rows["B + pwas at the true transform 0.2"]
    assert est["share_gaussians"] == true["share_gaussians"]
    assert est["align_error_cm"] is not None and true["align_error_cm"] is None
    firsts = []
    for name in ("agent A (first part)", "agent B (last part)"):
        with LogReader(out / rows[name]["log"]) as log:
            assert log.metadata.world_frame.startswith("first-camera:")
            firsts.append(log.read_poses(TOPIC_POSE_GT)[1][0])
    T_true = read_transform(out / "runs" / "s0_align_true.txt")
    np.testing.assert_allclose(T_true, np.linalg.inv(firsts[1]) @ firsts[0], atol=1e-9)
    T_est = read_transform(out / "runs" / "s0_align.txt")
    error = np.linalg.norm((np.linalg.inv(T_true) @ T_est)[:3, 3]) * 100
    assert error == pytest.approx(est["align_error_cm"], abs=1e-6)
    with LogReader(out / true["log"]) as log:
        step = log.metadata.provenance[-1]["operation"]
    np.testing.assert_allclose(step["transform"], T_true, atol=1e-9)  # merged at the truth
    assert "## Alignment" in (out / "results.md").read_text()
    aligned = json.loads((out / "runs" / "s0_align.json").read_text())["result"]
    assert aligned["on_frames"]["views"] >= 1  # refined on B's frames
    assert {"registration_error_cm", "drift_cm"} <= aligned["on_frames"].keys()
    # cross-agent scoring: B's map on A's frames starts at A's poses moved by the estimate
    from gscompress.io.trajectory import read_tum_trajectory
    from gscompress.pipeline.logs import pose_source

    start = read_tum_trajectory(out / "runs" / "s0_pwas_0p2_agent_b_xeval_start_a.txt")
    poses_a = pose_source(out / rows["agent A (first part)"]["log"]).T_world_cam
    np.testing.assert_allclose(start.T_world_cam, T_est @ poses_a, atol=1e-9)
    assert all(math.isfinite(rows["B + pwas 0.2"][key]) for key in CROSS)


def test_folded_spread_shares_and_the_default_merge_rerun_only_what_they_change(
    experiment: tuple[Path, Path, dict], tmp_path: Path
) -> None:
    seq, copy = experiment[0], _copy(experiment, tmp_path)
    again = _run(seq, copy, "--merge", "default", "--fold", "--spread")
    assert 0 < again["steps"] - again["reused"] < again["steps"]  # the SLAM runs were reused
    records = {p.stem: json.loads(p.read_text()) for p in (copy / "runs").glob("*.json")}
    shares = [s for s in records.values() if s.get("spec", {}).get("kind") == "share"]
    # (records of other tests' steps in the fixture's folder stay as they were)
    folded = [s for s in shares if s["spec"].get("fold")]
    assert len(folded) >= 2 and all(s["result"]["fold"] for s in folded)  # pwas and random
    assert all(s["spec"]["spread"] and s["result"]["spread"] for s in folded)
    assert "spread over space (`--spread`)" in (copy / "results.md").read_text()
    merges = [
        name
        for name, r in records.items()
        if r.get("spec", {}).get("kind") == "merge"
        and r["spec"].get("merge", {}).get("resolve") == "evidence"
    ]
    assert merges
    for name in merges:
        with LogReader(copy / "runs" / f"{name}.mcap") as log:
            assert log.metadata.provenance[-1]["operation"]["resolve"] == "evidence"
    assert "`gsc merge`'s default" in (copy / "results.md").read_text()
    assert "folds what it leaves out" in (copy / "results.md").read_text()


def test_shares_without_sums_or_with_ids_change_size_and_rerun_only_the_shares_and_their_readers(
    experiment: tuple[Path, Path, dict], tmp_path: Path
) -> None:
    seq, copy = experiment[0], _copy(experiment, tmp_path)
    before = {r["name"]: r for r in json.loads((copy / "results.json").read_text())}
    again = _run(seq, copy, "--strategies", "random,pwas", "--no-sums")
    # the shares of 2 strategies x 2 budgets and the whole map, each merged and scored
    assert again["steps"] - again["reused"] == 3 * 5
    after = {r["name"]: r for r in json.loads((copy / "results.json").read_text())}
    for name in ("B + pwas 0.2", "B + random 0.5", "B + A's full map"):
        assert after[name]["share_gaussians"] == before[name]["share_gaussians"]
        assert after[name]["share_bytes"] < before[name]["share_bytes"], name
    record = json.loads((copy / "runs" / "s0_pwas_0p2_share.json").read_text())
    assert record["spec"]["sums"] is False and record["result"]["sums"] is False
    assert record["spec"]["ids"] is False and record["result"]["ids"] is False
    assert "carry no PWAS sums (`--no-sums`)" in (copy / "results.md").read_text()
    assert "carry the Gaussians' ids" not in (copy / "results.md").read_text()
    again = _run(seq, copy, "--strategies", "random,pwas", "--no-sums", "--ids")
    assert again["steps"] - again["reused"] == 3 * 5  # the ids are in each share's spec
    with_ids = {r["name"]: r for r in json.loads((copy / "results.json").read_text())}
    for name in ("B + pwas 0.2", "B + random 0.5", "B + A's full map"):
        assert with_ids[name]["share_bytes"] > after[name]["share_bytes"], name
    assert "carry the Gaussians' ids (`--ids`)" in (copy / "results.md").read_text()


def test_shares_cut_for_b_sit_beside_the_blind_ones(
    experiment: tuple[Path, Path, dict], tmp_path: Path
) -> None:
    seq, copy = experiment[0], _copy(experiment, tmp_path)
    again = _run(seq, copy, "--strategies", "random,pwas,pwas-for-b")
    # only the new shares, their merges and their scoring ran: 2 budgets x 3 steps
    assert again["steps"] - again["reused"] == 6
    record = json.loads((copy / "runs" / "s0_pwas-for-b_0p2_share.json").read_text())
    assert record["spec"]["for"] and record["result"]["for"] == "s0_agent_b.mcap"
    assert record["result"]["strategy"] == "pwas" and record["result"]["request_bytes"] > 0
    assert "B + pwas-for-b 0.2" in (copy / "results.md").read_text()
    r = CliRunner().invoke(
        cli, ["experiment", str(seq), "-o", str(copy), "--strategies", "pwas,random,opacity-for-c"]
    )
    assert r.exit_code != 0 and "unknown strategies ['opacity-for-c']" in r.output
