"""`gsc experiment`'s defaults: the shares and merges of `gsc share` and `gsc merge`, a first look
that says what it will do, the paper's protocol and the whole study one flag away."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from gscompress.datasets.synthetic import write_synthetic_sequence
from gscompress.ops.merge import EXACT, MergeOptions
from gscompress.pipeline.experiment import ExperimentSettings, plan_size, resolve_settings
from gscompress.pipeline.experiment.estimate import render_passes
from gscompress.pipeline.experiment.execution import merge_options
from gscompress.pipeline.experiment.protocol import FULL_STUDY
from gscompress_cli.main import cli
from gscompress_cli.merge import merge as merge_command
from gscompress_cli.share import share as share_command


class Captured(Exception):
    """Raised by the stand-in for `run_experiment`, holding the settings it was given."""


def _settings(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, *options: str) -> ExperimentSettings:
    """The settings `gsc experiment` builds from `options` (the experiment itself not run)."""
    import gscompress_cli.experiment as experiment_command

    def capture(seq: Path, out: Path, settings: ExperimentSettings, **kwargs: object) -> None:
        raise Captured(settings)

    monkeypatch.setattr(experiment_command, "run_experiment", capture)
    tmp_path.joinpath("seq").mkdir(exist_ok=True)
    args = ["experiment", str(tmp_path / "seq"), "-o", str(tmp_path / "exp"), *options]
    r = CliRunner().invoke(cli, args)
    assert isinstance(r.exception, Captured), r.output
    settings = r.exception.args[0]
    assert isinstance(settings, ExperimentSettings)
    return settings


def _defaults(command: object) -> dict[str, object]:
    """Each option's default, by parameter name, as the click command declares it."""
    return {p.name: p.default for p in command.params}  # type: ignore[attr-defined]


def test_the_default_shares_and_merges_are_the_commands(monkeypatch, tmp_path) -> None:
    s = _settings(monkeypatch, tmp_path)
    share = _defaults(share_command)
    assert (s.fold, s.sums, s.ids, s.spread) == (
        share["fold"],
        share["sums"],
        share["ids"],
        share["spread"],
    )
    assert s.budget == share["budget"] and "pwas" in s.strategies
    merge = _defaults(merge_command)
    assert (s.merge_iters, s.merge_views, s.merge_lr_final) == (
        merge["iters"],
        merge["views"],
        merge["lr_final"],
    )
    fields = ("align", "icp", "resolve", "voxel", "margin", "share_rate", "by_view", "footprint")
    assert merge_options(s.merge_how) == MergeOptions(**{f: merge[f] for f in fields})


def test_the_papers_protocol_and_the_whole_study_are_one_flag_away(monkeypatch, tmp_path) -> None:
    paper = _settings(monkeypatch, tmp_path, "--protocol", "paper")
    assert not paper.fold and merge_options(paper.merge_how) == EXACT
    folded = _settings(monkeypatch, tmp_path, "--protocol", "paper", "--fold")
    assert folded.fold and folded.merge_how == "exact"  # (an option given still decides)
    first = _settings(monkeypatch, tmp_path)
    full = _settings(monkeypatch, tmp_path, "--full")
    assert {k: getattr(full, k) for k in FULL_STUDY} == FULL_STUDY
    assert plan_size(first) < plan_size(full)
    assert _settings(monkeypatch, tmp_path, "--full", "--seeds", "2").seeds == 2
    _, base = resolve_settings(first)
    assert 0 < render_passes(first, base, 16) < render_passes(full, base, 16)


def test_a_default_row_is_gsc_share_and_gsc_merge_run_by_hand(tmp_path: Path) -> None:
    """The experiment's row of B with A's PWAS share, run with the defaults, is what `gsc share`
    and `gsc merge` give with theirs on A's and B's logs: the same Gaussians in the share's
    map, as many bytes of it, the same merged map and the same PSNR. (The share file records
    its command line, which differs: the experiment's shares record none.)"""
    seq = write_synthetic_sequence(tmp_path / "room", 4, (64, 48))
    out = tmp_path / "exp"
    r = CliRunner().invoke(
        cli,
        [
            "experiment",
            str(seq),
            "-o",
            str(out),
            "--preset",
            "tiny",
            "--refine-poses",
            "0",
            "--no-lpips",
        ],
    )
    assert r.exit_code == 0, r.output
    steps = plan_size(ExperimentSettings(refine_poses=0))
    assert f"experiment: {steps} steps" in r.output and "protocol commands" in r.output
    assert "Protocol `commands`" in (out / "results.md").read_text()
    rows = {row["name"]: row for row in json.loads((out / "results.json").read_text())}
    row = rows["B + pwas 0.2"]
    runs = out / "runs"
    share = json.loads((runs / "s0_pwas_0p2_share.json").read_text())["result"]

    def gsc(*args: object) -> dict:
        got = CliRunner().invoke(cli, [*map(str, args), "--json"])
        assert got.exit_code == 0, got.output
        return json.loads(got.output)

    by_hand = gsc("share", runs / "s0_agent_a.mcap", tmp_path / "share.mcap")
    assert by_hand["selected"] == share["selected"] == row["share_gaussians"]
    assert by_hand["bytes"] == share["bytes"]  # the map as sent, byte for byte the same size
    from gscompress.io.mcap_log import read_map

    mine, theirs = read_map(tmp_path / "share.mcap"), read_map(runs / "s0_pwas_0p2_share.mcap")
    assert (mine.means == theirs.means).all() and (mine.importance == theirs.importance).all()
    gsc(
        "merge",
        runs / "s0_agent_b.mcap",
        tmp_path / "share.mcap",
        "--seq",
        seq,
        "-o",
        tmp_path / "merged.mcap",
    )
    merged = read_map(tmp_path / "merged.mcap")
    assert len(merged) == row["gaussians"]
    assert (merged.means == read_map(out / row["log"]).means).all()
    every = ExperimentSettings().every  # (the experiment's evaluation: every N-th frame)
    scores = gsc("eval", tmp_path / "merged.mcap", "--seq", seq, "--every", every, "--no-lpips")
    assert scores["psnr"] == row["psnr"]


def test_the_estimate_prices_each_kind_of_work_as_timed_on_two_frames(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Tracking-like iterations, mapping-like iterations and evaluation renders are counted
    apart and priced apart: one kind at a second a unit and the others free gives that kind's
    count; the pricing run maps the first frame and tracks and maps the second."""
    from gscompress.datasets import open_sequence
    from gscompress.pipeline.experiment import estimate as module

    first = _settings(monkeypatch, tmp_path, "--preset", "tiny")
    _, base = resolve_settings(first)
    work = module.plan_work(first, base, 16)
    assert min(work.parts()) > 0
    assert round(sum(work.parts())) == render_passes(first, base, 16)
    write_synthetic_sequence(tmp_path / "s", frames=2, size=(32, 24))
    sequence = open_sequence(tmp_path / "s")
    price = module.unit_seconds(sequence, base)
    assert min(price.parts()) > 0
    on_two = module.plan_work(first, base, len(sequence)).parts()
    for i, kind in enumerate(("tracking", "mapping", "renders")):
        priced = module.Work(**{kind: 1.0})
        monkeypatch.setattr(module, "unit_seconds", lambda *a, p=priced: p)
        assert module.estimate(first, base, sequence, steps=18)["seconds"] == on_two[i]
