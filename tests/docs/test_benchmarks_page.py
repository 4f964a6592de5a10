"""docs/benchmarks.md stays a page for readers: under 400 lines; each benchmark's section follows
the page's template (What, How, Machine, Result, Record, in that order) in at most 40 lines; and
its prose names no commit hashes and no clock times (the records carry those; reasoning about a
run belongs in its closing note, history in git)."""

from __future__ import annotations

import re

from support import ROOT

PAGE = ROOT / "docs" / "benchmarks.md"
MAX_LINES = 399
MAX_SECTION_LINES = 40
TEMPLATE = ("**What.**", "**How.**", "**Machine.**", "**Result.**", "**Record.**")
# A commit hash: 7 to 40 hex digits with at least one digit and one letter, standing alone.
COMMIT = re.compile(r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")
CLOCK = re.compile(r"\b\d{1,2}:\d{2}\b")


def sections() -> dict[str, list[str]]:
    """Every ``## `` section after the table of current figures: its lines, heading to the last
    non-blank line."""
    found: dict[str, list[str]] = {}
    name = None
    for line in PAGE.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            name = line[3:]
            found[name] = []
        if name is not None:
            found[name].append(line)
    found.pop("Current figures")
    for lines in found.values():
        while lines and not lines[-1].strip():
            lines.pop()
    return found


def test_the_page_is_under_400_lines():
    assert len(PAGE.read_text(encoding="utf-8").splitlines()) <= MAX_LINES


def test_every_section_follows_the_template_in_at_most_40_lines():
    assert sections(), "no benchmark sections found"
    wrong = {}
    for name, lines in sections().items():
        text = "\n".join(lines)
        places = [text.find(mark) for mark in TEMPLATE]
        if len(lines) > MAX_SECTION_LINES or -1 in places or places != sorted(places):
            wrong[name] = (len(lines), dict(zip(TEMPLATE, places)))
    assert wrong == {}


def test_the_prose_names_no_commit_hash_or_clock_time():
    hits = [
        f"line {number}: {match.group()}"
        for number, line in enumerate(PAGE.read_text(encoding="utf-8").splitlines(), start=1)
        if not line.startswith("![")
        for match in [*COMMIT.finditer(line), *CLOCK.finditer(line)]
    ]
    assert hits == []
