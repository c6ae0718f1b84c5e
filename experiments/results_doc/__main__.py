"""``python -m experiments.results_doc``: write docs/results.md from the records."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from experiments.results_doc import BENCH_RECORDS, DOC, RECORDS, SECTIONS, render_page
from experiments.results_doc.page import GENERATED, RecordError
from experiments.sparse_views.summary import check_doc

PROG = "python -m experiments.results_doc"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description="Write docs/results.md from the records under "
                                "experiments/records/ and benchmarks/records/ (a section whose record is missing is named, "
                                "not filled in).")
    p.add_argument("--doc", type=Path, default=DOC, help="the page to write (default %(default)s)")
    p.add_argument("--records", type=Path, default=RECORDS,
                   help="the studies' records folder (default %(default)s)")
    p.add_argument("--bench-records", type=Path, default=BENCH_RECORDS,
                   help="the benchmarks' records folder, for the GPU sections (default %(default)s)")
    args = p.parse_args(argv)
    try:
        check_doc(args.doc, GENERATED)  # a page the user wrote is never replaced
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    for flag, folder in (("--records", args.records), ("--bench-records", args.bench_records)):
        if not folder.is_dir():
            print(f"{PROG}: error: records folder {folder} "
                  f"{'is not a folder' if folder.exists() else 'does not exist'}; pass {flag} with the folder "
                  "that holds the records", file=sys.stderr)
            return 2
    try:
        text, missing = render_page(args.records, args.bench_records, SECTIONS)
    except (RecordError, KeyError, TypeError, ValueError) as exc:
        msg = (str(exc) if isinstance(exc, RecordError)
               else f"a record under {args.records} or {args.bench_records} lacks {exc!r}")
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
