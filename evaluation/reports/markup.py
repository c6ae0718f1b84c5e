"""How a table cell, a Markdown table, an HTML table and an HTML page are written: one
implementation for the results tables and report (:mod:`evaluation.reports.tables`,
:mod:`evaluation.reports.report`) and the study's report (:mod:`evaluation.study.report`)."""

from __future__ import annotations

import html
import math
import re

import numpy as np

__all__ = ["counted", "format_value", "markdown_table", "html_table", "html_page"]


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` and the noun in the number that fits: "1 run", "2 runs", "0 runs" (``plural``
    where adding "s" is wrong)."""
    n = int(n)
    return f"{n} {noun if n == 1 else (plural or noun + 's')}"


def format_value(v, digits: int) -> str:
    """A table cell: "-" for None and NaN, "yes" / "no" for a boolean, an integer as it is, a
    float with ``digits`` decimals, anything else as text."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return f"{v:.{digits}f}"
    return str(v)


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A GitHub-flavoured Markdown table of text cells ("|" in a cell escaped)."""
    def line(cells):
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"

    return "\n".join([line(header), "|" + "---|" * len(header)] + [line(r) for r in rows])


def html_table(header: list[str], rows: list[list[str]]) -> str:
    """An HTML table of text cells (escaped); numbers right-aligned (:func:`number_cells`)."""
    h = "".join(f"<th>{html.escape(x)}</th>" for x in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(x)}</td>" for x in r) + "</tr>" for r in rows)
    return number_cells(f"<table><tr>{h}</tr>{body}</table>")


_NUMBER_CELL = re.compile(r"<td>(\s*(?:[-+]?[\d.,]+(?:e[-+]?\d+)?\s*(?:%|s|dB|deg)?|-|\d+/\d+)\s*)</td>")


def number_cells(table: str) -> str:
    """``table`` (HTML) with the cells that hold a number (or "-", or "k/n") marked
    ``class="num"``, which the report's style sheet right-aligns; text stays left-aligned."""
    table = table.replace('<tr style="text-align: right;">', "<tr>")  # pandas' header alignment
    return _NUMBER_CELL.sub(r'<td class="num">\1</td>', table)


def command_html(argv: list[str]) -> str:
    """A command as HTML that wraps only between arguments: each flag stays on one line with its
    value (``class="arg"``, which the report's style sheet keeps from wrapping)."""
    import shlex

    groups: list[list[str]] = []
    for a in argv:
        if groups and groups[-1][0].startswith("--") and len(groups[-1]) == 1 and not a.startswith("--"):
            groups[-1].append(a)
        else:
            groups.append([a])
    return " ".join(f'<span class="arg">{html.escape(shlex.join(g))}</span>' for g in groups)


def html_page(title: str, css: str, body: str) -> str:
    """A whole HTML page: ``title``, the style sheet ``css`` and ``body`` (HTML)."""
    return (f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{css}</style></head><body>\n{body}\n</body></html>\n")
