"""One set of conventions for every `gsc` command: how it names its output, whether it writes
over one, whether it prints JSON; and what a percentage given as a number meant."""

from __future__ import annotations

from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from gscompress.errors import InputError
from gscompress.ops.budget import Budget
from gscompress.selection import percent_hint
from gscompress_cli.main import cli

READ_ONLY = {"info", "view"}
"""Commands that write no file."""
REUSED = {"experiment": "its -o folder is where a rerun finds the runs it reuses"}
"""Outputs a rerun is meant to find (so no --force)."""
OPTIONAL = {"eval": "--save-images"}
"""Commands whose file output is optional, named by this option (they print their results)."""


def options(name: str) -> set[str]:
    command = cli.get_command(click.Context(cli), name)
    assert command is not None
    return {o for p in command.params for o in getattr(p, "opts", [])}


def test_every_command_that_writes_names_its_output_overwrites_with_force_and_prints_json() -> None:
    names = cli.list_commands(click.Context(cli))
    assert len(names) >= 16
    for name in names:
        given = options(name)
        if name not in READ_ONLY - {"info"}:
            assert "--json" in given, name
        if name in READ_ONLY:
            continue
        output = OPTIONAL.get(name, "-o")
        assert output in given, name
        assert ("--force" in given) != (name in REUSED), name


@pytest.mark.parametrize(
    ("number", "hint"), [(30, "0.3 or 30%"), (100, "1 or 100%"), (0.5, ""), (300, ""), (1, "")]
)
def test_a_number_that_reads_as_a_percentage_gets_both_readings(number: float, hint: str) -> None:
    assert percent_hint(number) == hint
    assert percent_hint(float("nan")) == ""


def test_keep_30_and_budget_30_suggest_a_fraction_or_a_percentage(tmp_path: Path) -> None:
    log = tmp_path / "a.mcap"
    log.write_bytes(b"")  # (the options are refused before the file is read)
    runner = CliRunner()
    r = runner.invoke(cli, ["prune", str(log), "--keep", "30", "-o", str(tmp_path / "p.mcap")])
    assert r.exit_code == 2 and "did you mean 0.3 or 30%?" in r.output
    r = runner.invoke(cli, ["share", str(log), "--budget", "30", "-o", str(tmp_path / "s.mcap")])
    assert r.exit_code == 2 and "did you mean 0.3 or 30%?" in r.output
    assert "30kB" in r.output  # (bytes still suggested)
    with pytest.raises(InputError, match="did you mean"):
        Budget.parse("30")
    assert Budget.parse("30%").ratio == Budget.parse("0.3").ratio


def test_render_and_eval_write_over_earlier_pictures_only_with_force(tmp_path: Path) -> None:
    from gscompress.errors import OutputError
    from gscompress.pipeline.images import ImageOptions

    pictures = tmp_path / "pictures"
    ImageOptions(save_images=pictures).check()  # (a folder not made yet)
    pictures.mkdir()
    ImageOptions(save_images=pictures).check()  # (an empty one)
    (pictures / "rgb").mkdir()
    with pytest.raises(OutputError, match="pass `force`"):
        ImageOptions(save_images=pictures).check()
    ImageOptions(save_images=pictures, force=True).check()
    ImageOptions(save_images=None).check()
    for name in ("render", "eval"):
        assert "--force" in options(name)


def test_synth_and_share_take_their_output_with_o_or_as_the_older_argument(tmp_path: Path) -> None:
    runner = CliRunner()
    for args in (["-o", str(tmp_path / "a")], [str(tmp_path / "b")]):
        r = runner.invoke(cli, ["synth", *args, "--frames", "1", "--size", "16x12"])
        assert r.exit_code == 0, r.output
    assert (tmp_path / "a" / "rgb.txt").read_bytes() == (tmp_path / "b" / "rgb.txt").read_bytes()
    twice = ["synth", str(tmp_path / "c"), "-o", str(tmp_path / "d"), "--frames", "1"]
    r = runner.invoke(cli, twice)
    assert r.exit_code == 2 and "once" in r.output and not (tmp_path / "c").exists()
    r = runner.invoke(cli, ["synth", "--frames", "1"])
    assert r.exit_code == 2 and "missing the sequence's path" in r.output
