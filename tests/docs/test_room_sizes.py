"""The size limits issue 44 set for the code's rooms, read from the tree: no module in vecsim/,
service/ or bench/ is over 800 lines, and no class over 500 (a module past that holds two
concerns; split it by concern, not in halves)."""

from __future__ import annotations

import ast
from pathlib import Path

from support import ROOT

MAX_MODULE_LINES = 800
MAX_CLASS_LINES = 500
ROOMS = ("vecsim", "service", "bench")


def _modules() -> list[Path]:
    return sorted(path for room in ROOMS for path in (ROOT / room).rglob("*.py"))


def _classes(path: Path) -> list[tuple[str, int]]:
    """``(name, lines)`` of every class in ``path``, nested ones included, decorators counted."""
    tree = ast.parse(path.read_text(), str(path))
    return [
        (node.name, node.end_lineno - min([node.lineno, *(d.lineno for d in node.decorator_list)]) + 1)
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef) and node.end_lineno is not None
    ]


def test_the_rooms_hold_python_modules() -> None:
    assert len(_modules()) > 50, "the limits below would check nothing: where did the modules go?"


def test_no_module_is_over_800_lines() -> None:
    over = {
        str(path.relative_to(ROOT)): lines
        for path in _modules()
        if (lines := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert not over, f"modules over {MAX_MODULE_LINES} lines (split them by concern): {over}"


def test_no_class_is_over_500_lines() -> None:
    over = {
        f"{path.relative_to(ROOT)}:{name}": lines
        for path in _modules()
        for name, lines in _classes(path)
        if lines > MAX_CLASS_LINES
    }
    assert not over, f"classes over {MAX_CLASS_LINES} lines (split them by concern): {over}"
