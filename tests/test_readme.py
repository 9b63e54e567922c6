"""The README's walk runs as written: every `$ gsc ...` line of its console blocks, in order.

The only changes are of scale, so that it runs in seconds: the synthetic room is made at 48x36
instead of 160x120 and the SLAM runs use the tiny preset. Each command must exit 0.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from click.testing import CliRunner

from gscompress_cli.main import cli

README = Path(__file__).resolve().parent.parent / "README.md"


def readme_commands() -> list[list[str]]:
    """The `$ gsc ...` lines of the README's console blocks, split into words."""
    blocks = re.findall(r"```console\n(.*?)```", README.read_text(), flags=re.S)
    lines = [line[2:] for block in blocks for line in block.splitlines() if line.startswith("$ ")]
    return [shlex.split(line) for line in lines]


def at_test_scale(words: list[str]) -> list[str]:
    """The same command on a smaller room and with the tiny SLAM preset."""
    words = ["48x36" if w == "160x120" else w for w in words]
    if words[1] == "slam":
        words += ["--preset", "tiny"]
    return words


def test_the_readme_has_the_walk() -> None:
    verbs = [words[1] for words in readme_commands()]
    assert all(words[0] == "gsc" for words in readme_commands())
    for verb in ("synth", "slam", "prune", "share", "merge", "eval"):
        assert verb in verbs


@pytest.mark.slow
def test_every_command_of_the_walk_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    for words in readme_commands():
        words = at_test_scale(words)
        result = runner.invoke(cli, words[1:])
        assert result.exit_code == 0, f"{shlex.join(words)}\n{result.output}"
    assert Path("demo_out/robot_b_merged.mcap").is_file()
