"""The ``vecsim`` command.

Each subcommand lives with the code it runs; this module only parses the first word and hands
the rest of the arguments over. Each subcommand's module is imported when that subcommand runs,
so ``vecsim pod`` does not load the controller (nor ``vecsim controller`` the simulator).
"""

from __future__ import annotations

import sys
from collections.abc import Callable


def _pod(argv: list[str]) -> int:
    from service.pod.main import main

    return main(argv)


def _controller(argv: list[str]) -> int:
    from service.controller.main import main

    return main(argv)


def _up(argv: list[str]) -> int:
    from service.runner.main import main

    return main(argv)


def _demo(argv: list[str]) -> int:
    from service.demo import main

    return main(argv)


# subcommand -> (function taking the argv list and returning an exit code, one-line help)
COMMANDS: dict[str, tuple[Callable[[list[str]], int], str]] = {
    "pod": (_pod, "run one sim pod (FastAPI + uvicorn)"),
    "controller": (_controller, "run the controller"),
    "up": (_up, "start a local job: controller + N pods, StatefulSet-style"),
    "demo": (_demo, "start a local job and run a pipelined rollout on it"),
}


def _version() -> str:
    from service.launcher import checkout
    from vecsim import __version__

    return f"vecsim {__version__} from {checkout()}"


def _usage() -> str:
    lines = [_version(), "usage: vecsim <command> [options]", "", "commands:"]
    lines += [f"  {name:<12}{help_}" for name, (_, help_) in COMMANDS.items()]
    lines.append("\n'vecsim <command> --help' for a command's options.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0 if argv else 2
    if argv[0] == "--version":
        print(_version())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"vecsim: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    func, _ = COMMANDS[name]
    return int(func(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
