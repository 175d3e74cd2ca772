"""``gpumap`` command line: ``demo``, ``replay``, ``bench`` and ``info``.

Each subcommand lives with the code it drives and owns its own options; this module only
dispatches, so ``gpumap demo --help`` shows the demo's own help.
"""

from __future__ import annotations

import importlib
import logging
import sys

COMMANDS = {
    "demo": ("gpumap.sim.demo", "simulate the tank scene, map it, and score the map against truth"),
    "replay": ("gpumap.replay", "map a real recording (Oculus, ARIS, fan images + poses, ROS bag)"),
    "bench": ("bench.__main__", "speed against error sweep (run from the repository root)"),
    "info": ("gpumap.cli", "list the backends this machine can run"),
}


def info(argv: list[str] | None = None) -> int:
    import gpumap
    from gpumap.backends import make_backend

    spec = gpumap.SonarSpec.uniform(n_beams=4, n_bins=4)
    print(f"gpumap {gpumap.__version__}")
    names = gpumap.available_backends()
    for name in names:
        b = make_backend(name, spec, 1, None)
        print(f"  {name:<11} {b.device}")
    print(f"auto picks: {names[0]}")
    return 0


def _usage() -> str:
    lines = ["usage: gpumap COMMAND [options]   (gpumap COMMAND --help for its options)", "", "commands:"]
    lines += [f"  {k:<8} {v[1]}" for k, v in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"gpumap: unknown command {cmd!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if cmd == "info":
        return info(rest)
    if cmd == "bench" and "" not in sys.path and "." not in sys.path:
        sys.path.insert(0, "")  # bench/ lives in the source checkout, next to pyproject.toml
    try:
        mod = importlib.import_module(COMMANDS[cmd][0])
    except ModuleNotFoundError as e:
        if cmd == "bench":
            print(
                "gpumap bench runs from a source checkout: cd to it and run `python -m bench`",
                file=sys.stderr,
            )
            return 2
        raise e
    from gpumap.errors import BackendUnavailableError

    try:
        return int(mod.main(rest) or 0)
    except (BackendUnavailableError, ValueError) as e:  # bad input or machine: say it, no traceback
        print(f"gpumap {cmd}: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
