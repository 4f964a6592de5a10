"""The layering docs/api.md and README's "Layout" state, each rule read from the code itself:

- the trainer's side (``vecsim.client``, ``vecsim.transport``, training, the trainer adapters and
  the shared contract: every ``vecsim`` module outside ``vecsim.engine``) never imports the pod
  engine, neither in an ``import`` statement at any depth nor at run time;
- the library (``vecsim``) never imports ``service``;
- the pod and the controller never import each other (what they exchange lives in
  ``service.contract`` and ``service.http``);
- bench/ uses vecsim's and service's public names only: no private module, no private name;
- each ``bench/*.py`` script is one benchmark: it imports what it shares from ``bench/lib``, never
  from another script.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

from support import ROOT

ENGINE = ROOT / "vecsim" / "engine"


def imported_modules(path: Path) -> set[str]:
    """Every module an ``import`` statement in ``path`` names, at any depth (function bodies
    included), relative imports resolved against the file's package; ``from m import n`` names
    both ``m`` and ``m.n`` (``n`` may be a submodule)."""
    return {module for module, _name in imports(path)} | {f"{module}.{name}" for module, name in imports(path) if name}


def imports(path: Path) -> set[tuple[str, str]]:
    """``(module, name)`` for each import in ``path``: ``name`` is what ``from module import
    name`` takes, "" for a plain ``import module``."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    found: set[tuple[str, str]] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update((alias.name, "") for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            found.update((module, alias.name) for alias in node.names)
    return found


def _under(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def offenders(paths: list[Path], forbidden: tuple[str, ...]) -> dict[str, list[str]]:
    bad = {}
    for path in paths:
        hits = sorted(m for m in imported_modules(path) if _under(m, forbidden))
        if hits:
            bad[str(path.relative_to(ROOT))] = hits
    return bad


def python_files(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def trainer_side_files() -> list[Path]:
    """Every module of ``vecsim`` outside the engine: the client, the transport, training, the
    trainer adapters and the shared contract."""
    return [path for path in python_files("vecsim") if ENGINE not in path.parents]


def test_the_trainer_side_never_imports_the_engine():
    assert offenders(trainer_side_files(), ("vecsim.engine",)) == {}


def test_the_library_never_imports_the_service():
    assert offenders(python_files("vecsim"), ("service",)) == {}


def test_the_pod_and_the_controller_never_import_each_other():
    assert offenders(python_files("service/pod"), ("service.controller",)) == {}
    assert offenders(python_files("service/controller"), ("service.pod",)) == {}


def test_bench_imports_no_private_module_or_name_of_vecsim_or_service():
    private = {}
    for path in python_files("bench"):
        hits = sorted(
            f"{module}.{name}" if name else module
            for module, name in imports(path)
            if _under(module, ("vecsim", "service"))
            and any(part.startswith("_") for part in [*module.split("."), name] if part)
        )
        if hits:
            private[str(path.relative_to(ROOT))] = hits
    assert private == {}


def test_no_bench_script_imports_another_script():
    scripts = {path.stem for path in (ROOT / "bench").glob("*.py")}
    assert scripts, "no bench scripts found"
    crossing = {
        str(path.relative_to(ROOT)): hits
        for path in python_files("bench")
        if (hits := sorted(m for m in imported_modules(path) if m.split(".")[0] in scripts))
    }
    assert crossing == {}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def loaded_after_importing(paths: list[Path], wanted: str) -> list[str]:
    """Import the modules at ``paths`` in a fresh interpreter; return the modules under
    ``wanted`` that ended up loaded."""
    script = f"""
import importlib, json, sys
for name in {[module_name(path) for path in paths]!r}:
    importlib.import_module(name)
print(json.dumps(sorted(m for m in sys.modules if m == {wanted!r} or m.startswith({wanted!r} + "."))))
"""
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_importing_every_trainer_side_module_loads_no_engine_module():
    assert loaded_after_importing(trainer_side_files(), "vecsim.engine") == []


def test_importing_every_library_module_loads_no_service_module():
    assert loaded_after_importing(python_files("vecsim"), "service") == []
