"""``python -m benchmarks.results_doc``: write docs/results.md from the records."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.results_doc import DOC, RECORDS, SECTIONS, render_page
from benchmarks.results_doc.page import GENERATED, RecordError
from benchmarks.sparse_views.summary import check_doc

PROG = "python -m benchmarks.results_doc"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description="Write docs/results.md from the records under "
                                "benchmarks/records/ (a section whose record is missing is named, not filled in).")
    p.add_argument("--doc", type=Path, default=DOC, help="the page to write (default %(default)s)")
    p.add_argument("--records", type=Path, default=RECORDS, help="the records folder (default %(default)s)")
    args = p.parse_args(argv)
    try:
        check_doc(args.doc, GENERATED)  # a page the user wrote is never replaced
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    if not args.records.is_dir():
        print(f"{PROG}: error: records folder {args.records} "
              f"{'is not a folder' if args.records.exists() else 'does not exist'}; pass --records with the folder "
              "that holds the benchmark records", file=sys.stderr)
        return 2
    try:
        text, missing = render_page(args.records, SECTIONS)
    except (RecordError, KeyError, TypeError, ValueError) as exc:
        msg = str(exc) if isinstance(exc, RecordError) else f"a record under {args.records} lacks {exc!r}"
        print(f"{PROG}: error: {msg}", file=sys.stderr)
        return 2
    from runtime.atomic import atomic_path

    args.doc.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.doc) as tmp:
        tmp.write_text(text)
    for s in missing:
        print(f"left out (no record): {s.heading}")
    print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
