"""How a table cell, a Markdown table, an HTML table and an HTML page are written: one
implementation for the results tables and report (:mod:`evaluation.reports.tables`,
:mod:`evaluation.reports.report`) and the study's report (:mod:`evaluation.study.report`)."""

from __future__ import annotations

import html
import math

import numpy as np

__all__ = ["format_value", "markdown_table", "html_table", "html_page"]


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
    """An HTML table of text cells (escaped)."""
    h = "".join(f"<th>{html.escape(x)}</th>" for x in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(x)}</td>" for x in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def html_page(title: str, css: str, body: str) -> str:
    """A whole HTML page: ``title``, the style sheet ``css`` and ``body`` (HTML)."""
    return (f'<!DOCTYPE html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{css}</style></head><body>\n{body}\n</body></html>\n")
