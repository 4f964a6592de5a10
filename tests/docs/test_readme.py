"""The README stays true as the code moves: it names no test counts or suite times (they go stale
with every commit), and its "Layout" block matches the tree: every folder it names exists, and
every package and module of ``vecsim/`` is named there."""

from __future__ import annotations

import re

from support import ROOT

README = ROOT / "README.md"
STALE = re.compile(r"\b\d[\d,]* (?:of (?:the )?\d[\d,]* )?tests\b|\b\d+(?:\.\d+)?(?:-\d+(?:\.\d+)?)? min\b")


def layout_block() -> list[str]:
    text = README.read_text(encoding="utf-8")
    start = text.index("```", text.index("## Layout")) + 3
    return text[start : text.index("```", start)].strip("\n").splitlines()


def named() -> tuple[set[str], dict[str, set[str]]]:
    """Top-level folders the block names, and per folder the entries (``x/`` folders, ``x``
    modules) its indented lines name."""
    top: set[str] = set()
    inside: dict[str, set[str]] = {}
    context = ""
    for line in layout_block():
        head = re.split(r"\s{2,}(?=[a-z(`A-Z])", line.strip(), maxsplit=1)[0] if line.startswith("  ") else line
        if not line.startswith(" "):
            folders = []
            for token in line.split():  # the leading folders, up to the description
                if not token.endswith("/"):
                    break
                folders.append(token)
            top.update(folders)
            context = folders[0] if folders else context
        elif not line.startswith("    "):
            inside.setdefault(context, set()).update(head.split())
    return top, inside


def test_the_readme_names_no_test_counts_or_suite_times():
    assert STALE.findall(README.read_text(encoding="utf-8")) == []


def test_every_folder_the_layout_names_exists():
    top, inside = named()
    assert top and all((ROOT / folder).is_dir() for folder in top), top
    for folder, entries in inside.items():
        for entry in entries:
            path = ROOT / folder / entry
            assert path.is_dir() if entry.endswith("/") else path.with_suffix(".py").is_file(), path


def test_the_layout_names_every_package_and_module_of_the_library():
    _, inside = named()
    listed = inside["vecsim/"]
    library = {p.name + "/" for p in (ROOT / "vecsim").iterdir() if (p / "__init__.py").is_file()}
    library |= {p.stem for p in (ROOT / "vecsim").glob("*.py") if p.stem != "__init__"}
    assert library == listed
