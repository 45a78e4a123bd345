"""The ``piezo-stage`` command: one module per subcommand, each thin argument parsing
(``add_arguments``) and a ``main(args)`` over the core and io.

Every command turns bad input into one line on stderr and exit code 2; outputs are
written to a temporary file and renamed, so they are complete or absent.
"""

from __future__ import annotations

import importlib
import sys

from piezo_stage.cli._common import EXIT_SOLVER, Parser, die
from piezo_stage.core.errors import (
    BackendFault,
    DataError,
    PiezoStageError,
    RunError,
    SolverError,
)
from piezo_stage.process import stopping

COMMANDS = ("simulate", "invert", "excite", "gap", "launch", "demo", "experiment", "tune",
            "replay", "bag", "loop", "identify", "refit", "study", "bench", "raster", "play",
            "lifecycle", "move", "scan", "watch")


def build_parser(argv=None):
    """The parser of every subcommand (``args.fn`` is its ``main``); of the one
    subcommand ARGV names, when it names one (a command starts without importing the
    others' modules and what they import: `lifecycle` needs no numpy)."""
    p = Parser(prog="piezo-stage", description="piezo stage tools: simulate, identify, "
               "diagnose the sim-to-real gap, control through the ROS 2 node set")
    from piezo_stage import __version__
    p.add_argument("--version", action="version", version=f"piezo-stage {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, parser_class=Parser)
    words = sys.argv[1:] if argv is None else list(argv)
    first = next((w for w in words if not w.startswith("-")), None)
    named = first in COMMANDS and not any(w in ("-h", "--help", "--version")
                                          for w in words[:words.index(first)])
    for name in ((first,) if named and first is not None else COMMANDS):
        mod = importlib.import_module(f"piezo_stage.cli.{name}")
        s = sub.add_parser(name, help=mod.HELP)
        mod.add_arguments(s)
        s.set_defaults(fn=mod.main)
    return p


INPUTS = ("inp", "model", "config", "data", "validate", "fit", "holdout", "bag", "plant")
FILE_OUTPUTS = ("json", "out_model", "plot")  # and "out" where it names a file (not a folder)
DIR_COMMANDS = ("study", "demo", "launch", "experiment", "refit")  # whose --out is a folder


def check_paths(args):
    """Outputs never overwrite an input, and can be written: else DataError (exit 2)."""
    import os

    from piezo_stage.io.files import check_input, check_output
    for k in INPUTS:  # a file input is a regular, bounded file (bags are folders)
        p = getattr(args, k, None)
        if isinstance(p, str) and os.path.exists(p) and not os.path.isdir(p):
            check_input(p)
    ins = {os.path.realpath(p) for k in INPUTS if isinstance(p := getattr(args, k, None), str)}
    outs = [(k, p) for k in FILE_OUTPUTS + ("out", "report")
            if isinstance(p := getattr(args, k, None), str)]
    for k, p in outs:
        flag = "--" + k.replace("_", "-")
        if os.path.realpath(p) in ins:
            raise DataError(f"{flag} {p} is also an input: outputs never overwrite inputs")
        if k in FILE_OUTPUTS or (k == "out" and args.cmd not in DIR_COMMANDS):
            if os.path.isdir(p):
                raise DataError(f"{flag} {p} is a directory; give a file name")
            check_output(p)
            parent = os.path.dirname(os.path.abspath(p))
            while not os.path.exists(parent):
                parent = os.path.dirname(parent)
            if not os.access(parent, os.W_OK):
                raise DataError(f"{flag} {p}: {parent} is not writable")


def main(argv=None):
    stopping.running()  # SIGTERM and SIGHUP stop a command as Ctrl-C does
    try:
        args = build_parser(argv).parse_args(argv)
        check_paths(args)
        return args.fn(args) or 0
    except SolverError as e:  # the data were fine; the solver did not deliver
        die(str(e), EXIT_SOLVER)
    except (BackendFault, RunError) as e:  # the input was fine; the hardware or run failed
        die(str(e), 1)
    except PiezoStageError as e:
        die(str(e))
    except KeyboardInterrupt:
        return _stopped()
    except SystemError as e:  # a stop inside a compiled kernel: numba's dispatcher
        if not _stopped_within(e):  # returns with the KeyboardInterrupt set
            raise
        return _stopped()


def _stopped() -> int:
    """A stop: later signals are ignored from here to the exit (a second Ctrl-C, or a
    stop meeting the line being written, once escaped as a KeyboardInterrupt and the
    interpreter then died by the signal: exit -2 after the line), then the one line."""
    stopping.hold()
    line, code = stopping.stopped_line()
    sys.stderr.write(line + "\n")
    return code


def _stopped_within(error: BaseException) -> bool:
    """Whether a KeyboardInterrupt is in ``error``'s chain (cause or context)."""
    seen = set()
    e: BaseException | None = error
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


if __name__ == "__main__":
    sys.exit(main())
