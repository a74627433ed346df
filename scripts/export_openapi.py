#!/usr/bin/env python3
"""Write ``openapi.yaml`` from the FastAPI app, or with ``--check`` fail when it has drifted.

python scripts/export_openapi.py           # rewrite openapi.yaml
python scripts/export_openapi.py --check   # exit 1 (and show a diff) when the file is stale
"""

from __future__ import annotations

import argparse
import difflib
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def render() -> str:
    from services.api.app import create_app

    schema = create_app().openapi()
    return yaml.safe_dump(schema, sort_keys=False, allow_unicode=True, width=100)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--check", action="store_true", help="fail if the file differs from the app"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "openapi.yaml")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        current = args.out.read_text() if args.out.exists() else ""
        if current != text:
            diff = difflib.unified_diff(
                current.splitlines(), text.splitlines(), str(args.out), "app", lineterm=""
            )
            print("\n".join(list(diff)[:200]))
            print(f"{args.out} is out of date: run `make openapi`", file=sys.stderr)
            return 1
        print(f"{args.out} matches the app")
        return 0
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
