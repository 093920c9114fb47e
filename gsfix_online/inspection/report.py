"""A self-contained HTML report: tables of figures and, per view, its images side by side.

The page links the PNGs that sit beside it (relative paths), so a report folder can be copied
or served as is. Nothing here computes metrics; callers pass the tables they measured.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from gsfix_online.config_schema import atomic_write_text

Cell = str | int | float | None


@dataclass(frozen=True)
class Table:
    title: str
    columns: Sequence[str]
    rows: Sequence[Sequence[Cell]]


@dataclass(frozen=True)
class ViewRow:
    name: str  # e.g. "view 003"
    images: Mapping[str, str]  # caption -> path relative to the report file
    note: str = ""  # e.g. the planner's reason


@dataclass(frozen=True)
class Report:
    title: str
    tables: Sequence[Table] = ()
    views: Sequence[ViewRow] = ()
    notes: Sequence[str] = field(default_factory=tuple)


def _fmt(v: Cell) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        if math.isnan(v):
            return "–"
        return "∞" if math.isinf(v) else f"{v:.3f}" if abs(v) < 10 else f"{v:.2f}"
    return html.escape(str(v))


def render_table(t: Table) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in t.columns)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(v)}</td>" for v in r) + "</tr>" for r in t.rows)
    return f"<h2>{html.escape(t.title)}</h2><table><tr>{head}</tr>{body}</table>"


def render_html(r: Report) -> str:
    parts = [
        "<!doctype html><meta charset='utf-8'>",
        f"<title>{html.escape(r.title)}</title>",
        "<style>body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;"
        "margin-bottom:1em}td,th{border:1px solid #bbb;padding:2px 8px;text-align:right}"
        "th{background:#eee}figure{display:inline-block;margin:4px}figcaption{font-size:90%;"
        "text-align:center}img{max-width:320px;image-rendering:pixelated}</style>",
        f"<h1>{html.escape(r.title)}</h1>",
    ]
    parts += [f"<p>{html.escape(n)}</p>" for n in r.notes]
    parts += [render_table(t) for t in r.tables]
    if r.views:
        parts.append("<h2>Views</h2>")
    for v in r.views:
        figs = "".join(
            f"<figure><img src='{html.escape(p)}' alt='{html.escape(c)}'>"
            f"<figcaption>{html.escape(c)}</figcaption></figure>"
            for c, p in v.images.items()
        )
        note = f" <small>{html.escape(v.note)}</small>" if v.note else ""
        parts.append(f"<h3>{html.escape(v.name)}{note}</h3><div>{figs}</div>")
    return "\n".join(parts) + "\n"


def write_report(path: Path, r: Report) -> Path:
    """Write the page atomically (a reader never sees half a file)."""
    atomic_write_text(path, render_html(r))
    return path
