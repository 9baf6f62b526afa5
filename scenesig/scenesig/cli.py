"""The ``scenesig`` command line: one console script, one subcommand module per command (as evo does).

Every command lives in :mod:`scenesig.commands` as a module with ``register(groups)`` -- which adds its
parser to ``groups[""]`` (the top level) or to a group such as ``groups["map"]`` and sets
``_run=run`` -- and ``run(args) -> int``.  This file only assembles the parser and owns the one error
handler: :class:`scenesig.surveys.errors.DataError` (bad input, named file and line) and
:class:`scenesig.surveys.extras.MissingExtraError` (an optional dependency missing) become
``scenesig: error: ...`` and exit status 2; Ctrl-C exits 130, a closed output pipe 141.  Heavy imports
(GTSAM, Dask) happen inside the command that needs them, so ``scenesig --help`` stays fast.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from scenesig.surveys.errors import DataError
from scenesig.surveys.extras import MissingExtraError

#: command modules under ``scenesig.commands``, in the order ``scenesig --help`` lists them
COMMANDS = (
    "demo",
    "simulate",
    "build_map",
    "map_show",
    "map_update",
    "localise",
    "compare",
    "evaluate",
    "report",
    "experiment",
    "bench",
    "importers",
    "check",
    "aerial",
    "config",
    "ros2",
)

#: second-level command groups (``scenesig GROUP ACTION``); a group appears once a command uses it
GROUPS = {
    "bench": "Benchmarks that print JSON.",
    "map": "Inspect a map.",
    "experiment": "The paper's experiments.",
    "import": "Convert other data sets to survey runs.",
    "export": "Write results in other formats.",
    "aerial": "UAV image to satellite-map matching.",
    "config": "Settings: presets and every stage's resolved values.",
    "ros2": "Run as a ROS 2 node (needs a ROS 2 install).",
}


class _Groups(dict):
    """``groups`` handed to ``register``: the group's subparsers are created on first use, so a group no
    command has joined yet does not show up in ``--help``."""

    def __init__(self, top):
        super().__init__({"": top})
        self._top = top

    def __missing__(self, name):
        if name not in GROUPS:
            raise KeyError(f"unknown command group {name!r}; known: {', '.join(GROUPS)}")
        g = self._top.add_parser(name, help=GROUPS[name], description=GROUPS[name])
        sub = g.add_subparsers(dest=f"{name}_command", required=True, metavar="ACTION")
        self[name] = sub
        return sub


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="scenesig",
        description="Long-term visual localisation with scene signatures (McManus, Upcroft and Newman, "
                    "\"Learning place-dependent features for long-term vision-based localisation\", "
                    "Autonomous Robots 2015).")
    top = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    groups = _Groups(top)
    for name in COMMANDS:
        importlib.import_module(f"scenesig.commands.{name}").register(groups)
    return p


def main(argv=None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``), run the command, return its exit status."""
    parser = build_parser()
    # a benchmark parses its own arguments: ``scenesig bench NAME ARGS...`` hands ARGS on untouched
    args, extra = parser.parse_known_args(argv)
    if extra and not getattr(args, "_pass_extra", False):
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args._extra = extra
    from scenesig.runtime import configure

    configure()          # process-wide tuning (malloc, OpenCV threads): the command line's, not the library's
    try:
        return int(args._run(args) or 0)
    except (DataError, MissingExtraError) as exc:
        print(f"scenesig: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("scenesig: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader went away (``scenesig ... | head``): stop quietly, as Unix tools do
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
