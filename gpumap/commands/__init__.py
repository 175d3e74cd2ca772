"""``gpumap`` command line: the subcommands of :data:`COMMANDS` (``gpumap --help`` lists them).

One module per subcommand (``gpumap.commands.<name>``), each owning its own options (so
``gpumap demo --help`` shows the demo's own help) and importing the library, never another
command; what they share is in :mod:`gpumap.commands.common`. This package only dispatches.
"""

from __future__ import annotations

import importlib
import logging
import sys

from gpumap.commands.common import error_line, user_errors

__all__ = ["COMMANDS", "main"]

#: subcommand -> (its module in this package, one line of help)
COMMANDS = {
    "demo": ("demo", "simulate the tank scene, map it, and score the map against truth"),
    "replay": ("replay", "map a real recording (Oculus, ARIS, fan images + poses, ROS bag)"),
    "view": ("view", "serve a saved or refined map or a recording in the browser view ([viewer] "
             "extra)"),
    "export": ("export", "write a saved or refined map as OctoMap .bt (RViz, octovis) or .ply"),
    "merge": ("merge", "merge saved maps of one grid built from different pings into one"),
    "ros": ("ros", "a ROS 2 node that maps live sonar pings ([ros] extra)"),
    "ros-play": ("ros_play", "publish a recording as the ROS 2 node's sonar topics ([ros] extra)"),
    "refine": ("refine", "fit a recording's map so that pings rendered from it match its pings"),
    "plan": ("plan", "next best sonar views for a saved map, from its confidence layer"),
    "bench": ("bench", "speed against error sweep on this machine (results in --out)"),
    "info": ("info", "list the backends this machine can run"),
}


def _usage() -> str:
    lines = ["usage: gpumap COMMAND [options]   (gpumap COMMAND --help for its options)", "", "commands:"]
    lines += [f"  {k:<8} {v[1]}" for k, v in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print(_usage(), file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"gpumap: error: unknown command {cmd!r}: expected one of {', '.join(COMMANDS)} "
              "(see gpumap --help)", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("OpenGL").setLevel(logging.WARNING)  # not "No OpenGL_accelerate module loaded"
    prog = f"gpumap {cmd}"
    try:
        mod = importlib.import_module(f"{__name__}.{COMMANDS[cmd][0]}")
        return int(mod.main(rest) or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except user_errors() as e:  # bad input or machine: say it in one line, no traceback
        print(error_line(prog, e), file=sys.stderr)
        return 2

