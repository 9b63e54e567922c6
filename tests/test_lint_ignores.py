"""The complexity ignores in pyproject.toml may only shrink: each one must still be needed."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
COMPLEXITY = ("C901", "PLR0913", "PLR0915")


def per_file_ignores() -> dict[str, list[str]]:
    """pyproject.toml's ruff per-file ignores of the complexity rules, by file."""
    if sys.version_info < (3, 11):
        pytest.skip("reading pyproject.toml needs tomllib (Python 3.11)")
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    ignores = config["tool"]["ruff"]["lint"]["per-file-ignores"]
    return {path: [code for code in codes if code in COMPLEXITY] for path, codes in ignores.items()}


def test_every_complexity_ignore_is_still_needed() -> None:
    ruff = shutil.which("ruff") or str(Path(sys.executable).parent / "ruff")
    if not Path(ruff).exists():
        pytest.skip("ruff is not installed (the [dev] extra)")
    ignores = per_file_ignores()
    rules = ["--select", ",".join(COMPLEXITY), "--exit-zero", "--output-format", "json"]
    command = [ruff, "check", "--isolated", *rules, *ignores]
    found = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, check=True)
    offending = {
        (str(Path(d["filename"]).resolve().relative_to(ROOT)), d["code"])
        for d in json.loads(found.stdout)
    }
    stale = [
        f"{path}: {code}"
        for path, codes in ignores.items()
        for code in codes
        if (path, code) not in offending
    ]
    assert not stale, "no longer needed, take them off pyproject.toml: " + ", ".join(stale)
