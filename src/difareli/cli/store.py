"""difareli-store: inspect an encodings store.

    difareli-store verify <store> [--headers-only] [--limit N]

``verify`` loads every array of every record and reports missing or unreadable files, wrong shapes or
dtypes, bad meta and NaN/Inf values (``EncodingStore.verify(check_values=True)``), one line per problem,
naming the record and the encoding. Exit status: 0 healthy, 1 problems found, 2 bad usage (e.g. no store).
"""

from __future__ import annotations

import argparse
import sys

from difareli.errors import check_int, cli_entry
from difareli.data.store import EncodingStore


def verify(root: str, *, check_values: bool = True, limit: int | None = None) -> list[str]:
    """Problems of the store at ``root`` (first ``limit`` records only if given); empty when healthy."""
    store = EncodingStore.open(root)
    ids = store.ids()[:limit] if limit is not None else None
    return store.verify(ids, check_values=check_values)


@cli_entry("store")
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="difareli-store", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    v = sub.add_parser("verify", help="check every record's files, shapes, dtypes and values")
    v.add_argument("store", help="the store root (the folder holding store.json)")
    v.add_argument("--headers-only", action="store_true", help="skip loading values (no NaN/Inf check)")
    v.add_argument("--limit", type=int, default=None, help="check only the first N records")
    args = parser.parse_args(argv)
    check_int(args.limit, "--limit", 1, allow_none=True)
    n = len(EncodingStore.open(args.store))
    problems = verify(args.store, check_values=not args.headers_only, limit=args.limit)
    checked = min(n, args.limit) if args.limit else n
    for p in problems:
        print(p)
    what = "headers" if args.headers_only else "headers and values"
    print(f"{args.store}: {checked} record(s), {what} checked: "
          + (f"{len(problems)} problem(s)" if problems else "healthy"), file=sys.stderr)
    return 1 if problems else 0


def entry() -> None:
    """Console-script entry point: exit with main's status."""
    sys.exit(main())


if __name__ == "__main__":
    entry()
