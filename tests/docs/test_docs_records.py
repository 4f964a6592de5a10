"""docs/benchmarks.md and the records under ``out/`` stay in step: every record a doc cites (a path under
``out/bench/``; ``out/demo/`` and the like are where commands write, not records) exists,
and every committed file under ``out/`` is cited by docs/benchmarks.md (a figure without its record,
or a record no figure needs, is what this catches).

A benchmark writes new runs to ``out/bench/<name>.json``; those are not committed until the page
cites them, so the committed files are what is checked (``git ls-files``), not whatever a local run
left on disk.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from support import ROOT

REPO = ROOT
BENCHMARKS = REPO / "docs" / "benchmarks.md"
# A cited path runs until a character that cannot be in one of ours (backtick, space, comma, ...).
CITED = re.compile(r"out/bench/[A-Za-z0-9_./<>{}-]*")
MAX_LINE = 200


def docs() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def cited_paths(text: str) -> set[str]:
    """Paths under out/bench/ named in ``text``; placeholders such as ``out/bench/<name>.json`` are not paths."""
    found = {match.rstrip(".") for match in CITED.findall(text)}
    return {path for path in found if not any(c in path for c in "<>{}")}


def committed_records() -> list[str]:
    done = subprocess.run(
        ["git", "ls-files", "-z", "--", "out"], cwd=REPO, capture_output=True, text=True, timeout=30, check=True
    )
    return sorted(name for name in done.stdout.split("\0") if name)


def test_every_record_a_doc_cites_exists() -> None:
    missing = {
        f"{doc.relative_to(REPO)}: {path}"
        for doc in docs()
        for path in cited_paths(doc.read_text(encoding="utf-8"))
        if not (REPO / path).exists()
    }
    assert not missing, "cited but not in the repository:\n" + "\n".join(sorted(missing))


def test_every_committed_file_under_out_is_cited_by_the_benchmarks_page() -> None:
    records = committed_records()
    assert records, "no committed file under out/: the page's records are gone"
    page = BENCHMARKS.read_text(encoding="utf-8")
    uncited = [name for name in records if name not in page]
    assert not uncited, "committed under out/ but not cited by docs/benchmarks.md:\n" + "\n".join(uncited)


def test_the_benchmarks_page_has_no_line_over_200_characters() -> None:
    long_lines = [
        f"line {number}: {len(line)} characters"
        for number, line in enumerate(BENCHMARKS.read_text(encoding="utf-8").splitlines(), start=1)
        if len(line) > MAX_LINE
    ]
    assert not long_lines, "\n".join(long_lines)
