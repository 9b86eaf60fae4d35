"""The one ``uuomocap`` command line.

Each module in ``uuomocap.commands`` adds its verbs: a module may define
``register(subparsers)`` for top-level verbs and ``register_bench(subparsers)``
for ``uuomocap bench <name>``.  A verb's handler takes the parsed arguments and
returns an exit code (or None for 0).  User mistakes raise ``UserError`` and
print as one line, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from uuomocap import __version__
from uuomocap.commands import UserError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uuomocap",
        description=(
            "Motion capture from unstructured, unlabeled optical markers plus one video. "
            "Every verb takes --help; most take --json for machine-readable output."
        ),
    )
    parser.add_argument("--version", action="version", version=f"uuomocap {__version__}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    bench = sub.add_parser(
        "bench",
        help="benchmarks that print tables and write JSON",
        description="Benchmarks: speed and accuracy targets live here, never in unit tests.",
    )
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH")
    bench.set_defaults(func=lambda a: _missing(bench))
    import uuomocap.commands as pkg

    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"uuomocap.commands.{info.name}")
        if hasattr(mod, "register"):
            mod.register(sub)
        if hasattr(mod, "register_bench"):
            mod.register_bench(bench_sub)
    return parser


def _missing(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        rc = args.func(args)
    except UserError as exc:
        print(f"uuomocap: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("uuomocap: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # `uuomocap ... | head`: the reader left; what it did not read is nobody's error.  Point
        # stdout at devnull so the interpreter's final flush does not raise again.
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
