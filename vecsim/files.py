"""Writing a file whole, for anything in vecsim or beside it that caches or records to disk
(the engine's state and fixture caches, bench's records): a reader, or another process making
the same file, never sees a half-written one."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any


def write_whole(path: Path, write: Callable[[Path], Any]) -> None:
    """Make ``path`` by calling ``write`` on a hidden file beside it (named for this process),
    then renaming that file to ``path``. Returns None."""
    partial = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    write(partial)
    os.replace(partial, path)
