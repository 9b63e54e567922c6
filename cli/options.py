"""Reusable click options and parameter types shared by the `gsc` commands."""

from __future__ import annotations

import json
import shlex
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import click

F = TypeVar("F", bound=Callable[..., Any])


def force_option(f: F) -> F:
    """`--force`: allow overwriting existing outputs (never an input)."""
    return click.option(
        "--force",
        is_flag=True,
        help="Overwrite existing output files (inputs are never overwritten).",
    )(f)


def json_option(f: F) -> F:
    """`--json`: print one JSON object instead of text."""
    return click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")(f)


def seed_option(f: F) -> F:
    """`--seed N` for the random strategy."""
    return click.option(
        "--seed", type=int, default=0, show_default=True, help="Seed of the random strategy."
    )(f)


class Ratio(click.ParamType):
    """A fraction in (0, 1]; also accepts percentages such as `30%`."""

    name = "ratio"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> float:
        if isinstance(value, float):
            ratio = value
        else:
            text = str(value).strip()
            try:
                ratio = float(text[:-1]) / 100 if text.endswith("%") else float(text)
            except ValueError:
                self.fail(f"{value!r} is not a number", param, ctx)
        if not 0.0 < ratio <= 1.0:
            self.fail(f"{value} is outside (0, 1]", param, ctx)
        return ratio


def command_line() -> str:
    """The command line of this process, for provenance records."""
    return " ".join(shlex.quote(arg) for arg in ["gsc", *sys.argv[1:]])


def emit(result: dict[str, Any], as_json: bool, text: str) -> None:
    """Print a command's result: the JSON object with --json, else the text."""
    click.echo(json.dumps(result, indent=2, sort_keys=True) if as_json else text)
