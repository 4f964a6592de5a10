"""The shared venv's ``vecsim`` command: a launcher that names the checkout it runs.

An editable install (``scripts/setup.sh``) points the venv at one checkout. pip's own
``vecsim`` script fails with ``No module named 'service'`` once that checkout is gone; this
launcher, a shell script written over it, says which checkout is gone and how to point the venv
at another. ``vecsim --help`` and ``vecsim --version`` name the checkout that answers.

    python -m service.launcher "$venv/bin/vecsim"      # scripts/setup.sh, after installing
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import service

TEMPLATE = """#!/bin/sh
# vecsim, run from the checkout {checkout} (written by scripts/setup.sh: service/launcher.py)
if [ ! -f {cli} ]; then
  echo "vecsim: this venv runs the checkout at {checkout}, which is gone (no service/cli.py there);" >&2
  echo "vecsim: run scripts/setup.sh in a checkout to point the venv at it" >&2
  exit 1
fi
exec {python} -P -m service.cli "$@"
"""


def checkout() -> Path:
    """The checkout (or install) this ``service`` package runs from."""
    return Path(service.__file__).resolve().parents[1]


def write_launcher(path: Path, python: Path, root: Path) -> None:
    """Write the launcher at ``path``: it runs ``python -m service.cli`` while ``root`` holds
    ``service/cli.py``, else says that ``root`` is gone and exits 1."""
    path.write_text(
        TEMPLATE.format(
            checkout=root, cli=shlex.quote(str(root / "service" / "cli.py")), python=shlex.quote(str(python))
        )
    )
    path.chmod(0o755)


if __name__ == "__main__":
    write_launcher(Path(sys.argv[1]), Path(sys.executable), checkout())
