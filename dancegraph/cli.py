"""The ``dancegraph`` command.

Each subcommand is a thin shell: parse arguments, call the library, print a result. Subcommands
register themselves in ``build_parser`` through one ``_add_*`` function per area.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from dancegraph import __version__
from dancegraph.errors import DanceGraphError


def _print_json(obj) -> None:
    json.dump(obj, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dancegraph", description="Music in, dance out.")
    parser.add_argument("--version", action="version", version=f"dancegraph {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_version,):
        add(sub)
    return parser


def _add_version(sub) -> None:
    p = sub.add_parser("version", help="print the version as JSON")
    p.set_defaults(func=lambda args: _print_json({"dancegraph": __version__}))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        result = args.func(args)
    except DanceGraphError as exc:
        print(f"error [{exc.code}]: {exc.message}", file=sys.stderr)
        return 2
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
