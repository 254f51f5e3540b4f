"""The ``posefuse`` command line: thin wrappers over the packages, one error message per mistake.

The built-in command groups (:data:`BUILTIN_GROUPS`, in this order) and then the groups of other
installed packages: each entry point of the ``posefuse.commands`` group, in order of name, names
a ``register(subparsers)`` function that adds sub-commands (``set_defaults(func=...)``, the
function taking the parsed arguments and returning the exit status).
"""

from __future__ import annotations

import argparse
import os
import sys
from importlib.metadata import entry_points

from posefuse.cli import active, data, onboard, quickstart, record, run, serve, train
from posefuse.cli.common import HelpFormatter
from posefuse.estimator.core.errors import PosefuseError

ENTRY_POINT_GROUP = "posefuse.commands"
# The built-in groups, in the order of `posefuse --help`: append a module to add a group.
BUILTIN_GROUPS = (data, onboard, run, quickstart, active, train, serve, record)


def _register_plugins(sub) -> None:
    """The command groups of the ``posefuse.commands`` entry points, by name; one that fails to
    load or clashes with a command is left out with a warning, the others still work."""
    seen: set[str] = set()
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda ep: ep.name):
        if ep.name in seen:  # the same distribution found twice on sys.path
            continue
        seen.add(ep.name)
        try:
            ep.load()(sub)
        except Exception as exc:  # a broken plugin must not break the other commands
            print(
                f"posefuse: warning: commands {ep.name!r} ({ep.value}) not loaded: {exc}",
                file=sys.stderr,
            )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="posefuse",
        description="Multi-view 6D pose estimation of textureless, shiny parts from RGB frames.",
        epilog="`posefuse COMMAND --help` shows a command's options and their defaults.",
        formatter_class=HelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in BUILTIN_GROUPS:
        group.register(sub)
    _register_plugins(sub)
    for command in sub.choices.values():  # every command shows its defaults, plugins' too
        if command.formatter_class is argparse.HelpFormatter:
            command.formatter_class = HelpFormatter
    return parser


def main(argv: list[str] | None = None) -> int:
    if not sys.stderr.isatty():
        # progress bars into a log: a line every 30 s, not every update (tqdm reads TQDM_*;
        # worker processes inherit it)
        os.environ.setdefault("TQDM_MININTERVAL", "30")
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv[1:]  # what followed the command, for reports that name their command
    try:
        return int(args.func(args) or 0)
    except PosefuseError as exc:
        print(f"posefuse {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # unreadable/unwritable paths: name the file, no traceback
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"posefuse {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"posefuse {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
