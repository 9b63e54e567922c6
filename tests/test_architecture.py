"""docs/architecture.md's picture of the pipeline is the code's import graph."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import pytest

grimp = pytest.importorskip("grimp")  # (import-linter's, in the dev extra)

DOC = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"


def node(module: str) -> str | None:
    """The picture's node of a pipeline module: its module or package below `pipeline` (None:
    `pipeline/__init__` itself)."""
    parts = module.split(".")
    return parts[2] if len(parts) > 2 else None


def code_edges() -> tuple[set[str], set[tuple[str, str]]]:
    graph = grimp.build_graph("gscompress")
    modules = {m for m in graph.modules if m.startswith("gscompress.pipeline.")}
    nodes = {n for n in map(node, modules) if n}
    edges = set()
    for module in modules:
        for imported in graph.find_modules_directly_imported_by(module):
            inside = imported.startswith("gscompress.pipeline.")
            a, b = node(module), node(imported) if inside else None
            if a and b and a != b:
                edges.add((a, b))
    return nodes, edges


def drawn_edges() -> tuple[set[str], set[tuple[str, str]]]:
    block = re.search(r"```mermaid\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)
    assert block, "docs/architecture.md has no mermaid picture"
    nodes: set[str] = set()
    edges: set[tuple[str, str]] = set()
    for line in block.group(1).splitlines()[1:]:
        sides = [[n.strip() for n in side.split("&")] for side in line.split("-->")]
        nodes.update(n for side in sides for n in side if n)
        for sources, targets in itertools.pairwise(sides):
            edges.update((a, b) for a in sources for b in targets)
    return nodes, edges


def test_the_picture_draws_every_pipeline_module_and_import() -> None:
    code_nodes, code = code_edges()
    drawn_nodes, drawn = drawn_edges()
    assert drawn_nodes == code_nodes
    assert drawn == code, f"missing {sorted(code - drawn)}, extra {sorted(drawn - code)}"


def test_no_command_module_imports_another() -> None:
    _, code = code_edges()
    helpers = {"logs", "images", "refining", "aligning"}
    commands = {a for a, _ in code} | {b for _, b in code}
    commands -= helpers | {"experiment"}
    assert not {(a, b) for a, b in code if a in commands and b in commands}
