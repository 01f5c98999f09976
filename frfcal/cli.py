"""The ``frfcal`` command line.

Each sub-command lives in its own module under :mod:`frfcal.commands` and
exposes ``HELP`` (one line), ``configure(parser)`` and ``run(args) -> int``.
Command modules keep their top-level imports light (argparse only); heavy
imports happen inside ``run`` so that ``frfcal --help`` stays instant.

Errors a user can act on (bad file, unknown card, missing channel) are raised
by the layers as ``ValueError``/``OSError`` subclasses with a message naming
the file, card, channel or field; they are printed as one line and exit with
status 2; anything else as one line "internal error" and status 1. ``-v``/``--debug``
(before or after the sub-command) shows the traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

from frfcal import __version__

#: (command name, module) in the order ``frfcal --help`` lists them.
COMMANDS: tuple[tuple[str, str], ...] = (
    ("info", "frfcal.commands.info"),
    ("modes", "frfcal.commands.modes"),
    ("example", "frfcal.commands.example"),
    ("pretest", "frfcal.commands.pretest"),
    ("acquire", "frfcal.commands.acquire"),
    ("import-uff", "frfcal.commands.import_uff"),
    ("export-uff", "frfcal.commands.export_uff"),
    ("identify", "frfcal.commands.identify"),
    ("calibrate", "frfcal.commands.calibrate"),
    ("diagnose", "frfcal.commands.diagnose"),
    ("run", "frfcal.commands.run"),
    ("demo", "frfcal.commands.demo"),
    ("report", "frfcal.commands.report"),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="frfcal",
        description="Structural-dynamics test lab toolkit: FE models, pretest, "
        "stepped-sine acquisition, identification and calibration.",
    )
    parser.add_argument("--version", action="version", version=f"frfcal {__version__}")
    parser.add_argument("-v", "--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in COMMANDS:
        if importlib.util.find_spec(module_name) is None:
            continue
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.configure(p)
        # -v/--debug also after the sub-command (frfcal run x.toml -v); SUPPRESS keeps the global one otherwise
        p.add_argument("-v", "--debug", action="store_true", default=argparse.SUPPRESS,
                       help="show full tracebacks on errors")
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help()
        return 1
    from frfcal._malloc import keep_large_allocations

    keep_large_allocations()  # large temporaries reused, not page-faulted afresh (frfcal/_malloc.py)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("frfcal: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, KeyError) as exc:
        if args.debug:
            raise
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"frfcal {args.command}: error: {_short(message)}", file=sys.stderr)
        return 2
    except Exception as exc:  # a fault of frfcal itself, not of the input: still one line, the traceback on -v
        if args.debug:
            raise
        print(f"frfcal {args.command}: internal error: {type(exc).__name__}: {_short(exc)}\n"
              f"frfcal {args.command}: rerun with -v for the traceback and report it", file=sys.stderr)
        return 1


def _short(message, limit: int = 600) -> str:
    """An error message on one line (a long one cut, -v shows it whole)."""
    text = " ".join(str(message).split())
    return text if len(text) <= limit else text[: limit - 20] + " ... (-v: all of it)"


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
