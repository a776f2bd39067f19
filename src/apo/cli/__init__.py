"""Command line of apo: ``apo <command> ...``.

Argument parsing only; every command calls the library. Each command lives in its own module
``apo.cli.<name>`` exposing ``register(subparsers)``, which adds a sub-parser whose ``func``
default runs the command and returns the exit code.
"""

from __future__ import annotations

import os

# One OpenBLAS thread unless the user says otherwise, set before numpy is first imported:
# apo's matrix products are small (a few thousand rows at most), and OpenBLAS's worker
# threads cost more to start and spin after each product than they save (the 41-frame
# `apo analyze`: 0.06 s of 0.38 s CPU; docs/recognition.md, "The whole process").
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import gc
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

from apo.errors import ApoError


@contextmanager
def warnings_to_stderr(prefix: str) -> Iterator[None]:
    """Print the warnings raised inside the block as ``<prefix>: warning: <message>``.

    A user of the command line sees one line per warning (a mesh flipped inside-out, a
    model of implausible size), not Python's warning format with a source line.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield
        finally:
            for w in caught:
                print(f"{prefix}: warning: {w.message}", file=sys.stderr)


#: The sub-commands (module ``apo.cli.<name>`` each), in the order ``apo --help`` lists them.
COMMANDS = ("dof", "contacts", "analyze", "demo", "track", "report", "figures", "plan", "replay")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Return the top-level parser with every available sub-command registered.

    With ``only="analyze"`` or ``only="track"``, only that sub-command is registered (the
    other commands' modules are not imported: 0.1 s of CPU): what :func:`main` parses
    ``apo analyze ...`` and ``apo track ...`` with, the commands whose whole-process times
    are targets (docs/recognition.md, "The whole process"; docs/perception.md, "Session 5:
    speed"). Any other ``only`` registers every command.
    """
    parser = argparse.ArgumentParser(
        prog="apo",
        description="Assembly Plan from Observation: demonstration -> robot task model.",
    )
    from apo import __version__

    parser.add_argument("--version", action="version", version=f"apo {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    if only == "analyze":
        from apo.cli import analyze

        analyze.register(sub)
        return parser
    if only == "track":  # `apo track`: 4 s for 120 frames is a target (docs/perception.md)
        from apo.cli import track

        track.register(sub)
        return parser
    # Plain imports (tools see them); inside the function because the command modules
    # import this package. One line per command, in the order `apo --help` lists them.
    from apo.cli import analyze, contacts, demo, dof, figures, plan, replay, report, track

    for module in (dof, contacts, analyze, demo, track, report, figures, plan, replay):
        module.register(sub)
    return parser


@contextmanager
def _imports_settled(freeze: bool) -> Iterator[None]:
    """Import the command's modules with the cyclic garbage collector paused, then freeze them.

    Importing makes many objects and next to no garbage: a collection then only walks them
    (the 41-frame `apo analyze`: collections during the imports and the one at exit, which
    walks every object alive, about 3 % of its instructions). With ``freeze`` (the process's
    own command line, not a call from a program) the objects alive after the imports go to
    the collector's permanent generation (:func:`gc.freeze`): later collections skip them.
    """
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if freeze:
            gc.freeze()
        if was:
            gc.enable()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit code (0 ok, 1 failure, 2 bad input)."""
    given = list(sys.argv[1:] if argv is None else argv)
    # `apo analyze ...` needs the analyze parser only (the other commands' modules are
    # not imported: a few ms of every run, where the 41-frame target is 0.3 s); as
    # `apo track ...`
    with _imports_settled(argv is None):
        parser = build_parser(given[0] if given else None)
    args = parser.parse_args(given)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    try:
        return int(args.func(args))
    except ApoError as exc:
        print(f"apo {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader of stdout went away (``apo ... | head``): files are already written;
        # point stdout at devnull so that the interpreter's final flush does not fail again
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
