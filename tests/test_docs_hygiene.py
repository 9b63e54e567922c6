"""The project's text files keep to the point, and the documentation's links lead somewhere.

- No tracked text file dates anything by a work session or turn: figures are dated by commit
  and machine, and history lives in git and CHANGELOG.md. Other senses of the word (pytest's
  `scope="session"`, a viewer's or a server's session) are not work periods and pass.
- Every relative link of README.md and docs/*.md names a file that exists, and an anchor into a
  Markdown file names one of its headings.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

TEXT_SUFFIXES = (".md", ".py", ".toml", ".yaml", ".yml", ".txt", ".proto")
TEXT_NAMES = ("Makefile", ".ci/run")

WORK_PERIOD = re.compile(
    r"\b(?:work\s+)?(?:sessions?|turns?)\s+\d+(?:\s*(?:-|to|and)\s*\d+)?\b(?!\s?(?:°|deg))"
    r"|\b(?:in|since|until|till|before|after|during|from)\s+(?:the\s+)?"
    r"(?:last|previous|this|that|next|earlier|same|current)\s+(?:work\s+)?(?:session|turn)\b",
    re.IGNORECASE,
)
"""A work period named as one: a session or turn with its number, or one placed relative to
another ("since the last one"). A bare "session" (pytest's fixture scope, a client's connection)
is not one."""


def work_period_mentions(text: str) -> list[tuple[int, str]]:
    """(line number, words) of every place in `text` that dates something by a work period
    (the words may run over a line end)."""
    return [
        (text.count("\n", 0, match.start()) + 1, " ".join(match.group().split()))
        for match in WORK_PERIOD.finditer(text)
    ]


def tracked_text_files() -> list[str]:
    """The tracked files whose suffix or name marks them as text the project writes."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    names = [name for name in listed.decode().split("\0") if name]
    return sorted(
        name
        for name in names
        if (name.endswith(TEXT_SUFFIXES) or name in TEXT_NAMES) and (ROOT / name).is_file()
    )


def doc_files() -> list[str]:
    pages = sorted(str(path.relative_to(ROOT)) for path in (ROOT / "docs").glob("*.md"))
    return ["README.md", *pages]


FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
CODE_SPAN = re.compile(r"`+[^`\n]*`+")
LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.MULTILINE)


def anchor_of(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = heading.replace("`", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors_in(markdown: str) -> set[str]:
    """Every heading anchor of a Markdown text (repeats numbered as GitHub numbers them)."""
    seen: dict[str, int] = {}
    anchors = set()
    for heading in HEADING.findall(FENCE.sub("", markdown)):
        base = anchor_of(heading)
        count = seen.get(base, 0)
        anchors.add(base if count == 0 else f"{base}-{count}")
        seen[base] = count + 1
    return anchors


def broken_links(path: Path) -> list[str]:
    """The relative links of Markdown file `path` whose file (or heading) does not exist."""
    text = path.read_text(encoding="utf-8")
    prose = CODE_SPAN.sub("", FENCE.sub("", text))
    broken = []
    for target in LINK.findall(prose):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # https:, mailto:
            continue
        name, _, anchor = target.partition("#")
        linked = (path.parent / name).resolve() if name else path
        if not linked.exists():
            broken.append(f"{target}: no such file")
        elif anchor and linked.suffix == ".md" and anchor not in anchors_in(linked.read_text()):
            broken.append(f"{target}: no such heading")
    return broken


@pytest.mark.parametrize("name", tracked_text_files())
def test_no_work_periods(name: str) -> None:
    text = (ROOT / name).read_text(encoding="utf-8", errors="replace")
    assert work_period_mentions(text) == [], f"{name} dates things by work period"


@pytest.mark.parametrize("name", doc_files())
def test_relative_links_resolve(name: str) -> None:
    assert broken_links(ROOT / name) == [], f"{name} has broken links"


def test_the_work_period_rule_is_precise() -> None:
    """The rule catches numbered sessions and turns and relative ones, not other sessions."""
    caught = [
        "Until sess" + "ion 21 the machine was an EPYC",
        "measured in Sess" + "ions 30 and 31",
        "as the README gave it before the last sess" + "ion",
        "since the previous tu" + "rn",
        "the tu" + "rn 4 runs",
        "used SplaTAM's rule alone. Sess" + "ion\n22's table",
    ]
    passed = [
        '@pytest.fixture(scope="session")',
        "a Foxglove session shows the layout",
        "each worker opens a session to the server",
        "turn 90 degrees about x",
        "the camera turns 15 deg per frame",
    ]
    assert [line for line in caught if not WORK_PERIOD.search(line)] == []
    assert [line for line in passed if WORK_PERIOD.search(line)] == []


def test_broken_links_are_found(tmp_path: Path) -> None:
    (tmp_path / "there.md").write_text("# A heading: `with code`\n\n## Twice\n\n## Twice\n")
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](there.md) [ok](there.md#a-heading-with-code) [ok](there.md#twice-1)\n"
        "[web](https://example.org/x) [self](#top)\n\n# Top\n\n"
        "[gone](missing.md) [bad anchor](there.md#nowhere)\n"
        "```\n[in code](ignored.md)\n```\n`[span](ignored.md)`\n"
    )
    assert broken_links(page) == ["missing.md: no such file", "there.md#nowhere: no such heading"]
