"""The ``vecsim`` command.

Each subcommand lives with the code it runs; this module only parses the first word and hands
the rest of the arguments over. The service modules are imported lazily so that importing the
library (``vecsim``) never imports ``service``.
"""

from __future__ import annotations

import importlib
import sys

# subcommand -> (module, function taking argv list and returning an exit code, one-line help)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "pod": ("service.pod.main", "main", "run one sim pod (FastAPI + uvicorn)"),
    "controller": ("service.controller.main", "main", "run the controller"),
    "up": ("service.runner.main", "main", "start a local job: controller + N pods, StatefulSet-style"),
    "demo": ("service.demo", "main", "start a local job and run a pipelined rollout on it"),
}


def _usage() -> str:
    lines = ["usage: vecsim <command> [options]", "", "commands:"]
    lines += [f"  {name:<12}{help_}" for name, (_, _, help_) in COMMANDS.items()]
    lines.append("\n'vecsim <command> --help' for a command's options.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"vecsim: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, func_name, _ = COMMANDS[name]
    func = getattr(importlib.import_module(module_name), func_name)
    return int(func(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
