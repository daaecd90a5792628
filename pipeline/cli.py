"""Command-line entry point: ``python -m pipeline <subcommand> ...``.

Each subcommand is a module with two functions::

    def add_arguments(parser: argparse.ArgumentParser) -> None: ...
    def main(args: argparse.Namespace) -> int: ...

(and, for a subcommand whose work a rerun resumes, ``INTERRUPTED_HINT``: what the Ctrl-C line adds)
and one line in :data:`SUBCOMMANDS` below, mapping the subcommand's name to that module's import
path. Modules are imported only when their subcommand runs (or shows its own ``--help``), so a heavy import
(open3d, Dask) in one subcommand does not slow down the others. The module's docstring's first line
is the subcommand's one-line help (read from the module's source for the listing, which imports none).

Errors: a user mistake anywhere is raised as :class:`calib.errors.InputError`; :func:`main` prints it
as one line ``error: <message>`` on stderr and returns 2, without a traceback. Ctrl-C is one line too,
``interrupted``, and status 130: every file is written atomically, so what was finished is kept (and a
run resumes from it). Anything else is a bug and keeps its traceback. Error messages and log messages pass
through :func:`pipeline.terminal.printable`: they quote names read from files, which must not drive the
terminal.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import importlib.util
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from calib.errors import InputError
from pipeline.terminal import FoldingStreamHandler, PrintableFormatter, printable

#: Subcommand name -> import path of its module (see the module docstring). Add yours here.
SUBCOMMANDS: dict[str, str] = {
    "run": "pipeline.commands.run",
    "batch": "pipeline.commands.batch",
    "stages": "pipeline.commands.stages",
    "eval": "pipeline.evaluate",
    "synth": "pipeline.lab.synth.cli",
    "params": "pipeline.commands.params",
    "bench": "pipeline.commands.bench",
    "warmup": "pipeline.commands.warmup",
    "calibrate": "pipeline.commands.calibrate",
}

#: Exit status for a user error (as argparse uses for a bad command line).
USAGE_ERROR = 2
#: Exit status after Ctrl-C (128 + SIGINT, as shells report a command the signal ended).
INTERRUPTED = 130


def _first_line(text: str | None) -> str:
    return (text or "").strip().splitlines()[0] if text and text.strip() else ""


def _summary(module_path: str) -> str:
    """The first line of a subcommand module's docstring, read from its source without importing the module.

    The help listing names every subcommand; importing each for its docstring would load all their
    dependencies (open3d, matplotlib, numba: seconds) to print a dozen lines. Empty when the source cannot
    be read (a module made in memory).
    """
    try:
        path = _module_file(module_path)
        source = path.read_text(encoding="utf-8") if path is not None else None
    except (ImportError, ValueError, OSError):
        return ""
    return _first_line(ast.get_docstring(ast.parse(source))) if source else ""


def _module_file(module_path: str) -> Path | None:
    """The source file of a module of one of this project's packages, found without importing it or the packages
    that hold it (``importlib.util.find_spec`` of ``a.b.c`` imports ``a.b``: for ``pipeline.lab.synth.cli`` that
    is the synthetic renderer and scipy, which a help listing has no use for); None when not found."""
    top, *inner = module_path.split(".")
    spec = importlib.util.find_spec(top)
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        module = Path(folder).joinpath(*inner)
        for path in (module.with_suffix(".py"), module / "__init__.py"):
            if path.is_file():
                return path
    return None


def build_parser(chosen: str | None = None) -> argparse.ArgumentParser:
    """The parser, with one sub-parser per entry of :data:`SUBCOMMANDS`.

    Only the `chosen` subcommand's module is imported (None: none); the others get sub-parsers with their
    one-line summary (`_summary`) and no arguments, enough for the help listing and to parse a command line
    that names `chosen`.
    """
    parser = argparse.ArgumentParser(
        prog="python -m pipeline",
        description="Markerless motion capture: silhouettes -> visual shape -> articulated EM tracker.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    subparsers = parser.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=True)
    for name, module_path in SUBCOMMANDS.items():
        if name != chosen:
            subparsers.add_parser(name, help=_summary(module_path))
            continue
        module = importlib.import_module(module_path)
        summary = _first_line(module.__doc__)
        sub = subparsers.add_parser(name, help=summary, description=module.__doc__,
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(sub)
        sub.set_defaults(_module=module)
    return parser


def start_workers_early(argv: Sequence[str]) -> None:
    """Start the fork server of a ``run`` with local workers (``--workers N``, N > 1, no ``--scheduler``) now,
    before the run command's own imports.

    The server imports the per-frame tasks' modules once (:data:`pipeline.worker_modules.WORKER_MODULES`) and
    every worker is a fork of it (:func:`pipeline.engine.executors.start_worker_server`). Started here, its
    imports overlap this process's (the run command imports the tracker: most of a second), and the workers
    are ready when the first frames are. This look at the command line only decides when the server starts:
    the parser proper reads it, and a server started for nothing costs its imports' CPU.
    """
    from pipeline.engine.executors import usable_cpus

    look = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    look.add_argument("--workers", type=int, default=usable_cpus())
    look.add_argument("--scheduler")
    try:
        known, _ = look.parse_known_args(argv)
    except argparse.ArgumentError:  # the parser proper says what is wrong
        return
    if known.workers > 1 and not known.scheduler:
        from pipeline.engine.executors import start_worker_server
        from pipeline.worker_modules import WORKER_MODULES

        start_worker_server(WORKER_MODULES)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: ``sys.argv[1:]``), run the subcommand and return its exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = next((word for word in argv if not word.startswith("-")), None)
    if chosen == "run":
        start_workers_early(argv)
    parser = build_parser(chosen if chosen in SUBCOMMANDS else None)
    args = parser.parse_args(argv)
    handler = FoldingStreamHandler(sys.stderr)
    handler.setFormatter(PrintableFormatter("%(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, handlers=[handler], force=True)
    try:
        return args._module.main(args)
    except InputError as error:
        print(f"error: {printable(str(error))}", file=sys.stderr)  # it may quote names read from files
        return USAGE_ERROR
    except KeyboardInterrupt:  # Ctrl-C: the user stopped it, and every file written so far is whole
        print(f"interrupted{getattr(args._module, 'INTERRUPTED_HINT', '')}", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:  # the reader went away (`... | head`): not an error of ours, no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's own flush at exit must not fail
        return 0
