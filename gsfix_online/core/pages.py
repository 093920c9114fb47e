"""A self-contained HTML report: tables, plots, and per view its images side by side or under a
before/after slider.

The page opens in a browser straight from the file system with nothing else running: it links
the PNGs that sit beside it by relative paths (so a report folder can be copied or served as
is), embeds its plots as ``data:`` URIs, and its slider is a few lines of inline JavaScript over
an ``<input type=range>``; nothing is fetched from the network. Nothing here computes metrics;
callers pass the tables and series they measured.
"""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gsfix_online.core.io import atomic_write_text

Cell = str | int | float | None
IMG_PX = 320  # displayed width of view images


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
    # (before caption, after caption): two of ``images`` shown under one slider
    compare: tuple[str, str] | None = None


@dataclass(frozen=True)
class Plot:
    title: str
    png: bytes  # embedded as a data: URI


@dataclass(frozen=True)
class Report:
    title: str
    tables: Sequence[Table] = ()
    views: Sequence[ViewRow] = ()
    notes: Sequence[str] = field(default_factory=tuple)
    plots: Sequence[Plot] = ()


# ----------------------------------------------------------------------------------------------
# Plots (matplotlib, Agg canvas: no display, no global backend switch)
# ----------------------------------------------------------------------------------------------


def _figure(width_in: float, height_in: float) -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), dpi=100, layout="constrained")


def stage_times_figure(seconds: Mapping[str, float]) -> Any:  # -> matplotlib Figure
    """Horizontal bars: seconds per stage (NaN and missing stages left out)."""
    items = [(k, float(v)) for k, v in seconds.items() if v is not None and math.isfinite(v)]
    fig = _figure(6.4, 1.2 + 0.3 * len(items))
    ax = fig.add_subplot()
    names = [k for k, _ in items]
    ax.barh(range(len(items)), [v for _, v in items], color="#4c72b0")
    ax.set_yticks(range(len(items)), names)
    ax.invert_yaxis()  # first stage on top
    ax.set_xlabel("seconds")
    ax.set_title("Time per stage")
    for i, (_, v) in enumerate(items):
        ax.annotate(f" {v:.1f} s", (v, i), va="center", fontsize=8)
    return fig


def psnr_figure(
    views: Sequence[str],  # x labels, e.g. "000"
    psnr_db: Mapping[str, Sequence[float | None]],  # stage -> one PSNR per view (None: unscored)
) -> Any:  # -> matplotlib Figure
    """PSNR per view, one line of markers per stage or baseline."""
    fig = _figure(max(6.4, 0.35 * len(views) + 2.5), 3.6)
    ax = fig.add_subplot()
    x = list(range(len(views)))
    for stage, values in psnr_db.items():
        y = [math.nan if v is None else float(v) for v in values]
        ax.plot(x, y, marker="o", markersize=4, linewidth=1, label=stage)
    ax.set_xticks(x, views, rotation=90 if len(views) > 12 else 0, fontsize=8)
    ax.set_xlabel("view")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title("PSNR per view against ground truth")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncols=2, loc="best")
    return fig


# What a node was busy with, by the message type it handled or the work it named
# (runtime/timeline.py), grouped for the chart; other messages are bookkeeping.
TIMELINE_PHASES = {
    "rgbd": "map frames", "fine-tune": "fine-tune GSFixer", "repair": "repair (GSFixer)",
    "distil": "distil", "repaired_view": "distil", "render_request": "render",
    "render_reply": "render", "plan": "plan", "write": "write outputs",
}  # fmt: skip
PHASE_COLOURS = {
    "map frames": "#2ca02c", "fine-tune GSFixer": "#d62728", "repair (GSFixer)": "#9467bd",
    "distil": "#ff7f0e", "render": "#1f77b4", "plan": "#8c564b", "write outputs": "#e377c2",
    "bookkeeping": "#7f7f7f",
}  # fmt: skip


def timeline_figure(
    spans: Sequence[Mapping[str, Any]],  # {"node", "label", "t0", "t1"}, wall seconds
    cpu: Sequence[Mapping[str, Any]],  # {"t", "cpu_s": {node: CPU seconds so far}}
    cpu_used: tuple[float, int] | None = None,  # (the nodes' CPU seconds, the machine's cores)
) -> Any:  # -> matplotlib Figure
    """A Gantt chart of a graph run: per node a row of busy spans coloured by what the node did
    (``TIMELINE_PHASES``), and under them, shaded, the cores the node used (from the CPU
    samples; the band's height is one core)."""
    names = sorted({str(s["node"]) for s in spans} | {n for c in cpu for n in c["cpu_s"]})
    t0 = min([float(s["t0"]) for s in spans] + [float(c["t"]) for c in cpu], default=0.0)
    t1 = max([float(s["t1"]) for s in spans] + [float(c["t"]) for c in cpu], default=1.0)
    fig = _figure(9.0, 1.6 + 0.5 * max(len(names), 1))
    ax = fig.add_subplot()
    row = {n: i for i, n in enumerate(names)}
    bars: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for s in spans:
        phase = TIMELINE_PHASES.get(str(s["label"]), "bookkeeping")
        bars.setdefault((str(s["node"]), phase), []).append(
            (float(s["t0"]) - t0, float(s["t1"]) - float(s["t0"]))
        )
    for phase, colour in PHASE_COLOURS.items():
        drawn = False
        for n in names:
            if (n, phase) in bars:
                label = None if drawn else phase
                ax.broken_barh(bars[n, phase], (row[n] - 0.42, 0.5), color=colour, label=label)
                drawn = True
    for n in names:  # cores in use between two samples, as a band under the row's bars
        pts = [(float(c["t"]), float(c["cpu_s"][n])) for c in cpu if n in c["cpu_s"]]
        if len(pts) > 1:
            xs = [p[0] - t0 for p in pts]
            use = [0.0] + [
                min((b[1] - a[1]) / max(b[0] - a[0], 1e-9), 1.0)
                for a, b in zip(pts, pts[1:], strict=False)
            ]
            base = row[n] + 0.45
            ax.fill_between(xs, base, [base - 0.35 * u for u in use], step="pre",
                            color="0.6", linewidth=0)  # fmt: skip
    ax.set_yticks(range(len(names)), names)
    ax.set_ylim(len(names) - 0.5, -0.5)
    ax.set_xlim(0, max(t1 - t0, 1e-3))
    ax.set_xlabel("seconds since the first node started")
    title = "What each node did (bars) and the CPU it used (grey, band height = 1 core)"
    if cpu_used is not None:
        seconds, cores = cpu_used
        used = seconds / max((t1 - t0) * cores, 1e-9)
        title += f"\n{t1 - t0:.0f} s wall; the nodes used {used:.0%} of {cores} cores"
    ax.set_title(title, fontsize=9)
    ax.grid(axis="x", alpha=0.3)
    ax.legend(fontsize=7, ncols=4, loc="upper center", bbox_to_anchor=(0.5, -0.18))
    return fig


def figure_png(fig: Any) -> bytes:
    """A figure as PNG bytes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


# ----------------------------------------------------------------------------------------------
# HTML
# ----------------------------------------------------------------------------------------------

STYLE = (
    "body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;margin-bottom:1em}"
    "td,th{border:1px solid #bbb;padding:2px 8px;text-align:right}th{background:#eee}"
    "figure{display:inline-block;margin:4px;vertical-align:top}figcaption{font-size:90%;"
    f"text-align:center}}img{{width:{IMG_PX}px;image-rendering:pixelated}}"
    ".cmp{position:relative;display:inline-block;line-height:0}.cmp img{display:block}"
    ".cmp img.before{position:absolute;top:0;left:0;clip-path:inset(0 50% 0 0)}"
    f".cmp input{{width:{IMG_PX}px;margin:4px 0 0}}img.plot{{width:auto;max-width:100%}}"
)
PLOTS_END = "<!-- end of plots -->"  # where add_plot puts a later plot
# the slider uncovers the "before" image from the left; value = its visible percentage
SLIDE_JS = (
    "this.parentNode.querySelector('img.before').style.clipPath="
    "'inset(0 '+(100-this.value)+'% 0 0)'"
)


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


def _img(path: str, caption: str, cls: str = "") -> str:
    c = f" class='{cls}'" if cls else ""
    return f"<img{c} src='{html.escape(path)}' alt='{html.escape(caption)}'>"


def render_compare(v: ViewRow) -> str:
    """The before image over the after image, split by a range slider (50 % at first)."""
    assert v.compare is not None
    before, after = v.compare
    if before not in v.images or after not in v.images:
        raise ValueError(f"{v.name}: compare names {before!r} and {after!r}, images hold "
                         f"{', '.join(v.images)}")  # fmt: skip
    return (
        "<figure><div class='cmp'>"
        + _img(v.images[after], after, "after")
        + _img(v.images[before], before, "before")
        + f"<input type='range' min='0' max='100' value='50' oninput=\"{SLIDE_JS}\""
        f" aria-label='{html.escape(before)} / {html.escape(after)}'>"
        f"</div><figcaption>◀ {html.escape(before)} | {html.escape(after)} ▶</figcaption>"
        "</figure>"
    )


def _plot_html(p: Plot) -> str:
    data = base64.b64encode(p.png).decode("ascii")
    return (
        f"<h2>{html.escape(p.title)}</h2>"
        f"<img class='plot' src='data:image/png;base64,{data}' alt='{html.escape(p.title)}'>"
    )


def render_html(r: Report) -> str:
    parts = [
        "<!doctype html><meta charset='utf-8'>",
        f"<title>{html.escape(r.title)}</title>",
        f"<style>{STYLE}</style>",
        f"<h1>{html.escape(r.title)}</h1>",
    ]
    parts += [f"<p>{html.escape(n)}</p>" for n in r.notes]
    parts += [render_table(t) for t in r.tables]
    parts += [_plot_html(p) for p in r.plots]
    parts.append(PLOTS_END)
    if r.views:
        parts.append("<h2>Views</h2>")
    for v in r.views:
        figs = render_compare(v) if v.compare else ""
        figs += "".join(
            f"<figure>{_img(p, c)}<figcaption>{html.escape(c)}</figcaption></figure>"
            for c, p in v.images.items()
        )
        note = f" <small>{html.escape(v.note)}</small>" if v.note else ""
        parts.append(f"<h3>{html.escape(v.name)}{note}</h3><div>{figs}</div>")
    return "\n".join(parts) + "\n"


def add_plot(path: Path, plot: Plot) -> None:
    """Add a plot to a page written earlier, after its other plots (e.g. a run's timeline,
    drawn once every node of the graph that wrote the page has stopped)."""
    text = path.read_text()
    if PLOTS_END not in text:
        raise ValueError(f"{path}: not a report page of this version (no plots marker)")
    atomic_write_text(path, text.replace(PLOTS_END, _plot_html(plot) + "\n" + PLOTS_END, 1))


def write_report(path: Path, r: Report) -> Path:
    """Write the page atomically (a reader never sees half a file)."""
    atomic_write_text(path, render_html(r))
    return path
