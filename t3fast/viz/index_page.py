"""``index.html`` of a demo folder: the metrics tables, per-horizon curves, the pictures and
links to the 3D views, in one self-contained page (inline SVG, no scripts)."""

from __future__ import annotations

import html
import os
from pathlib import Path
from urllib.parse import quote

from t3fast.evaluation.report import metrics_markdown

HORIZONS = ("0s", "1s", "2s", "3s")
#: line colours of the methods, in order (matplotlib's tab10); later methods reuse them dashed
COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
           "#17becf")
PLOT_W, PLOT_H = 340, 230
MARGIN = {"left": 44, "right": 12, "top": 26, "bottom": 36}

_CSS = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 24px auto; max-width: 1200px; padding: 0 16px; color: #222; }
table { border-collapse: collapse; margin: 8px 0 20px; font-variant-numeric: tabular-nums; }
th, td { border: 1px solid #ccc; padding: 3px 8px; }
th { background: #f2f2f2; }
td.num { text-align: right; }
.plots { display: flex; flex-wrap: wrap; gap: 16px; align-items: flex-start; }
.legend { list-style: none; padding: 0; margin: 0; }
.legend svg { vertical-align: middle; margin-right: 6px; }
figure { margin: 0 0 16px; }
figure img { max-width: 100%; border: 1px solid #ddd; }
"""


def _stroke(n: int) -> str:
    """SVG stroke attributes of the ``n``-th method's line."""
    dash = ' stroke-dasharray="6 3"' if (n // len(COLOURS)) % 2 else ""
    return f'stroke="{COLOURS[n % len(COLOURS)]}" stroke-width="2"{dash}'


def _table_html(rows: list[str]) -> str:
    """A markdown table (header, alignment row, body rows) as an HTML table."""
    split = [[cell.strip() for cell in row.strip().strip("|").split("|")] for row in rows]
    header, align, body = split[0], split[1], split[2:]
    right = [a.endswith(":") for a in align]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in header)
    lines = ["<table>", f"<tr>{head}</tr>"]
    for row in body:
        cells = "".join(f'<td{" class=num" if r else ""}>{html.escape(c)}</td>' for c, r in zip(row, right))
        lines.append(f"<tr>{cells}</tr>")
    return "\n".join(lines + ["</table>"])


def metrics_html(results: dict[str, dict], title: str = "") -> str:
    """The tables of :func:`t3fast.evaluation.report.metrics_markdown` (same numbers) as HTML."""
    out, table = [], []
    for line in metrics_markdown(results, title).splitlines() + [""]:
        if line.startswith("|"):
            table.append(line)
            continue
        if table:
            out.append(_table_html(table))
            table = []
        if line.strip():
            out.append(f"<p>{html.escape(line)}</p>")
    return "\n".join(out)


def horizon_plot(results: dict[str, dict], metric: str, label: str) -> str:
    """Inline SVG: ``results[method][metric][h]`` (percent) against the horizons 0..3 s, one
    line per method; a missing (null) value breaks its line."""
    plot_w = PLOT_W - MARGIN["left"] - MARGIN["right"]
    plot_h = PLOT_H - MARGIN["top"] - MARGIN["bottom"]
    values = [v for r in results.values() for h in HORIZONS if (v := r[metric].get(h)) is not None]
    top = max(10.0, 10.0 * -(-max(values, default=0.0) // 10))  # next multiple of 10

    def xy(k: int, v: float) -> tuple[float, float]:
        return (MARGIN["left"] + plot_w * k / (len(HORIZONS) - 1), MARGIN["top"] + plot_h * (1 - v / top))

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{PLOT_W}" height="{PLOT_H}" '
             f'viewBox="0 0 {PLOT_W} {PLOT_H}" role="img" aria-label="{html.escape(label)} per horizon">',
             f'<text x="{PLOT_W / 2}" y="16" text-anchor="middle" font-size="13">{html.escape(label)}</text>']
    for tick in range(0, int(top) + 1, max(10, int(top) // 5 // 10 * 10)):
        _, y = xy(0, tick)
        parts.append(f'<line x1="{MARGIN["left"]}" x2="{PLOT_W - MARGIN["right"]}" y1="{y:.1f}" y2="{y:.1f}" '
                     f'stroke="#e3e3e3"/><text x="{MARGIN["left"] - 6}" y="{y + 4:.1f}" text-anchor="end" '
                     f'font-size="11">{tick}</text>')
    for k, h in enumerate(HORIZONS):
        x, _ = xy(k, 0)
        parts.append(f'<text x="{x:.1f}" y="{PLOT_H - MARGIN["bottom"] + 16}" text-anchor="middle" '
                     f'font-size="11">{h}</text>')
    parts.append(f'<text x="{MARGIN["left"] + plot_w / 2}" y="{PLOT_H - 4}" text-anchor="middle" '
                 f'font-size="11">horizon</text>')
    for n, (name, r) in enumerate(results.items()):
        colour = COLOURS[n % len(COLOURS)]
        points = [xy(k, v) if (v := r[metric].get(h)) is not None else None for k, h in enumerate(HORIZONS)]
        path, pen = [], "M"
        for p in points:
            if p is None:
                pen = "M"
                continue
            path.append(f"{pen}{p[0]:.1f},{p[1]:.1f}")
            pen = "L"
        if path:
            parts.append(f'<path d="{" ".join(path)}" fill="none" {_stroke(n)}>'
                         f"<title>{html.escape(name)}</title></path>")
        parts += [f'<circle cx="{p[0]:.1f}" cy="{p[1]:.1f}" r="2.5" fill="{colour}"/>' for p in points if p]
    return "\n".join(parts + ["</svg>"])


def _legend(names: list[str]) -> str:
    items = "".join(f'<li><svg width="24" height="8"><line x1="0" x2="24" y1="4" y2="4" {_stroke(n)}/></svg>'
                    f"{html.escape(name)}</li>" for n, name in enumerate(names))
    return f'<ul class="legend">{items}</ul>'


def _href(path: Path, out_dir: Path) -> str:
    """A URL of ``path`` relative to a page in ``out_dir`` (both absolute or relative to the
    current folder). Resolved first, so ``..`` and symbolic links count as the filesystem sees them."""
    return quote(Path(os.path.relpath(path.resolve(), out_dir.resolve())).as_posix())


def write_index(out_dir: str | Path, results: dict[str, dict], title: str, pictures: list[Path],
                views: list[Path]) -> Path:
    """Write ``out_dir/index.html``; returns its path.

    results: the ``metrics.json`` mapping (method -> scores, see
    :func:`t3fast.evaluation.report.evaluate_methods`); pictures: PNG/GIF files shown inline;
    views: 3D viewer pages linked. All paths as the file writers return them: absolute or
    relative to the current folder (not to ``out_dir``); the page links them relative to
    itself, so the folder can be moved as a whole.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    body = [f"<h1>{html.escape(title or 't3fast results')}</h1>", "<h2>Metrics</h2>", metrics_html(results),
            "<h2>Per-horizon occupancy forecasting</h2>", '<div class="plots">',
            horizon_plot(results, "miou", "mIoU (%)"), horizon_plot(results, "iou", "IoU (%)"),
            _legend(list(results)), "</div>"]
    if views:
        body.append("<h2>3D views</h2>\n<ul>")
        body += [f'<li><a href="{_href(Path(v), out_dir)}">{html.escape(Path(v).name)}</a></li>' for v in views]
        body.append("</ul>")
    if pictures:
        body.append("<h2>Pictures</h2>")
        body += [f'<figure><img src="{_href(Path(p), out_dir)}" alt="{html.escape(Path(p).name)}" loading="lazy">'
                 f"<figcaption>{html.escape(Path(p).name)}</figcaption></figure>" for p in pictures]
    page = ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{html.escape(title or 't3fast results')}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
            + "\n".join(body) + "\n</body>\n</html>\n")
    path = out_dir / "index.html"
    path.write_text(page, encoding="utf-8")
    return path
