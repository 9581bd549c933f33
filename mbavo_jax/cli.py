"""The ``mbavo`` command line: ``mbavo jacobians | synth | eval | track | deblur | bench``.

Known errors (bad input files, bad options) print one line ``mbavo: error: ...`` and exit 1.
"""

from __future__ import annotations

import argparse
import json
import sys

__all__ = ["main"]


class UserError(Exception):
    """A problem with the user's input: reported as one line, exit status 1."""


def _cmd_jacobians(args) -> int:
    from .paper import cross_validate, format_table

    results = cross_validate(seed=args.seed)
    if args.format == "json":
        print(json.dumps([r.as_dict() for r in results], indent=2, ensure_ascii=False))
    else:
        print(format_table(results))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mbavo", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("jacobians", help="cross-validate the supplement's Jacobians against autodiff (float64)")
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.add_argument("--seed", type=int, default=0, help="seed of the random samples (default 0)")
    p.set_defaults(func=_cmd_jacobians)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"mbavo: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("mbavo: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
