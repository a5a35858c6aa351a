"""``report.html``: one self-contained page per run (no network, no scripts from elsewhere).

The page holds the run's figure (inline base64 PNG), a DBH histogram (inline SVG), the run's
metrics (every number of metrics.json, flattened, each cell tagged ``data-key`` with its
dotted path so tests compare the page with the file), the parameters, the warnings and a
table of the trees or stems. Written through :func:`stemmap.io.atomic.atomic_write`.
"""

from __future__ import annotations

import base64
import html
import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from stemmap.io.atomic import atomic_write

__all__ = ["dbh_histogram_svg", "flatten_metrics", "format_number", "write_report"]

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:1.5em auto;
max-width:1100px;color:#222;padding:0 1em}
h1{font-size:1.4em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:.85em}td,th{border:1px solid #ddd;padding:2px 6px}
th{background:#f3f3f3;text-align:left}td.n{text-align:right;font-variant-numeric:tabular-nums}
.warn{background:#fff4e0;border-left:4px solid #e69500;padding:.4em .8em;margin:.3em 0}
img{max-width:100%;height:auto;border:1px solid #ddd}.scroll{max-height:420px;overflow:auto}
.headline{font-size:1.05em;background:#eef6ee;padding:.5em .8em;border-left:4px solid #2a7}
"""


def format_number(v: Any) -> str:
    """The text a number gets in the page (tests parse it back): ``repr`` precision for
    floats, ``null`` for None / NaN, as is for the rest."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "null" if not math.isfinite(v) else repr(v)
    return str(v)


def flatten_metrics(m: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """Dotted-path leaves of a metrics dict; lists of numbers stay one leaf (shown joined),
    long lists (> 20 items) are summarised as ``[n items]``."""
    out: list[tuple[str, Any]] = []
    for k, v in m.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.extend(flatten_metrics(v, key + "."))
        elif isinstance(v, (list, tuple)) and len(v) > 20:
            out.append((key, f"[{len(v)} items]"))
        else:
            out.append((key, v))
    return out


def dbh_histogram_svg(
    diameters: ArrayLike, *, bin_cm: float = 5.0, width: int = 520, height: int = 220
) -> str:
    """An inline SVG bar chart of DBH in ``bin_cm`` classes (counts above the bars)."""
    d = 100.0 * np.asarray(diameters, dtype=np.float64).reshape(-1)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return "<p>no diameters</p>"
    lo = bin_cm * math.floor(d.min() / bin_cm)
    hi = bin_cm * (math.floor(d.max() / bin_cm) + 1)
    edges = np.arange(lo, hi + 0.5 * bin_cm, bin_cm)
    counts, _ = np.histogram(d, edges)
    ml, mb, mt = 40, 36, 16
    pw, ph = width - ml - 10, height - mb - mt
    cmax = max(int(counts.max()), 1)
    bw = pw / len(counts)
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'role="img" aria-label="DBH histogram">',
        f'<line x1="{ml}" y1="{mt + ph}" x2="{ml + pw}" y2="{mt + ph}" stroke="#333"/>',
    ]
    for i, c in enumerate(counts):
        h = ph * c / cmax
        x = ml + i * bw
        parts.append(
            f'<rect x="{x + 1:.1f}" y="{mt + ph - h:.1f}" width="{bw - 2:.1f}" height="{h:.1f}" '
            f'fill="#4a9a5a"><title>{edges[i]:g}-{edges[i + 1]:g} cm: {c}</title></rect>'
        )
        if c:
            parts.append(
                f'<text x="{x + bw / 2:.1f}" y="{mt + ph - h - 3:.1f}" font-size="10" '
                f'text-anchor="middle">{c}</text>'
            )
        parts.append(
            f'<text x="{x:.1f}" y="{mt + ph + 14}" font-size="10" '
            f'text-anchor="middle">{edges[i]:g}</text>'
        )
    parts.append(
        f'<text x="{ml + pw:.1f}" y="{mt + ph + 14}" font-size="10" '
        f'text-anchor="middle">{edges[-1]:g}</text>'
    )
    parts.append(
        f'<text x="{ml + pw / 2}" y="{height - 4}" font-size="11" text-anchor="middle">'
        f"DBH class (cm, {bin_cm:g} cm wide)</text>"
    )
    parts.append(
        f'<text x="12" y="{mt + ph / 2}" font-size="11" text-anchor="middle" '
        f'transform="rotate(-90 12 {mt + ph / 2})">trees</text></svg>'
    )
    return "".join(parts)


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]], cls: str = "") -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = []
    for r in rows:
        cells = "".join(
            f'<td class="n">{html.escape(format_number(v))}</td>'
            if isinstance(v, (int, float)) and not isinstance(v, bool)
            else f"<td>{html.escape(str(v))}</td>"
            for v in r
        )
        body.append(f"<tr>{cells}</tr>")
    return f'<table class="{cls}"><tr>{head}</tr>{"".join(body)}</table>'


def write_report(
    path: str | os.PathLike[str],
    *,
    title: str,
    headline: str,
    metrics: Mapping[str, Any],
    figure_png: bytes | None = None,
    diameters: ArrayLike | None = None,
    table_header: Sequence[str] = (),
    table_rows: Sequence[Sequence[Any]] = (),
    parameters: Mapping[str, Any] | None = None,
    warnings: Sequence[str] = (),
    files: Sequence[str] = (),
) -> None:
    """Write the self-contained report page.

    Parameters
    ----------
    path : output file (``report.html``)
    title, headline : page title and the one-line result under it
    metrics : the run's metrics.json content (JSON-clean: no NaN); every leaf is shown with
        ``data-key="dotted.path"`` and the text of :func:`format_number`
    figure_png : the run's figure (PNG bytes), inlined as a data URI
    diameters : DBH of the mapped trees / stems (m) for the histogram
    table_header, table_rows : the per-tree (per-stem) table
    parameters : the command's options
    warnings : shown highlighted at the top
    files : the products written beside the report (relative names)
    """
    esc = html.escape
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>{esc(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{esc(title)}</h1><p class='headline' id='headline'>{esc(headline)}</p>",
    ]
    for w in warnings:
        parts.append(f"<div class='warn'>warning: {esc(w)}</div>")
    if figure_png is not None:
        b64 = base64.b64encode(figure_png).decode("ascii")
        parts.append(f"<h2>Map</h2><img id='figure' alt='map' src='data:image/png;base64,{b64}'>")
    if diameters is not None:
        parts.append("<h2>DBH distribution</h2>" + dbh_histogram_svg(diameters))
    rows = []
    for k, v in flatten_metrics(metrics):
        rows.append(
            f"<tr><td>{esc(k)}</td><td class='n' data-key='{esc(k)}'>{esc(format_number(v))}"
            "</td></tr>"
        )
    parts.append(
        "<h2>Metrics</h2><p>Every number of metrics.json (docs/outputs.md explains each).</p>"
        f"<table id='metrics'><tr><th>key</th><th>value</th></tr>{''.join(rows)}</table>"
    )
    if parameters:
        prow = [(k, v if isinstance(v, (int, float)) else str(v)) for k, v in parameters.items()]
        parts.append("<h2>Parameters</h2>" + _table(("option", "value"), prow))
    if table_rows:
        parts.append(
            f"<h2>Trees ({len(table_rows)})</h2><div class='scroll'>"
            + _table(table_header, table_rows, "trees")
            + "</div>"
        )
    if files:
        parts.append("<h2>Files</h2><ul>" + "".join(f"<li>{esc(f)}</li>" for f in files) + "</ul>")
    parts.append("</body></html>")
    with atomic_write(path) as fh:
        fh.write("\n".join(parts))
