"""The layering docs/api.md states: the library (``vecsim``) never imports ``service``; the pod and
the controller never import each other (what they exchange lives in ``service.contract`` and
``service.http``); the trainer's client imports no simulator and no torch."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

from support import ROOT


def imported_modules(path: Path) -> set[str]:
    """Every module an ``import`` statement in ``path`` names, at any depth (function bodies
    included), relative imports resolved against the file's package."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                found.add(".".join([*base, *([node.module] if node.module else [])]))
            elif node.module:
                found.add(node.module)
    return found


def offenders(package: str, forbidden: tuple[str, ...]) -> dict[str, list[str]]:
    bad = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        hits = sorted(m for m in imported_modules(path) if any(m == f or m.startswith(f + ".") for f in forbidden))
        if hits:
            bad[str(path.relative_to(ROOT))] = hits
    return bad


def test_the_library_never_imports_the_service():
    assert offenders("vecsim", ("service",)) == {}


def test_the_pod_and_the_controller_never_import_each_other():
    assert offenders("service/pod", ("service.controller",)) == {}
    assert offenders("service/controller", ("service.pod",)) == {}


def test_importing_every_library_module_loads_no_service_module():
    script = """
import importlib, json, pkgutil, sys
import vecsim
for info in pkgutil.walk_packages(vecsim.__path__, "vecsim."):
    importlib.import_module(info.name)
print(json.dumps(sorted(m for m in sys.modules if m == "service" or m.startswith("service."))))
"""
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout.strip().splitlines()[-1]) == []
