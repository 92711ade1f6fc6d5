"""The demo's index.html: metrics table, per-horizon SVG curves, pictures and 3D view links."""

from __future__ import annotations

import json
import re
from pathlib import Path

from t3fast.viz.index_page import write_index

METRICS = Path(__file__).parents[2] / "benchmarks" / "results" / "wm-test-metrics.json"


def _results() -> dict[str, dict]:
    results = json.loads(METRICS.read_text())
    results["copy_paste"]["miou"]["2s"] = None  # a gap in a curve
    return results


def test_index_has_table_curves_pictures_and_views(tmp_path):
    results = _results()
    pictures = [Path("scene-t00.png"), tmp_path / "scene-t00.gif"]
    views = [tmp_path / "views" / "scene 0.html"]
    page = write_index(tmp_path, results, "demo <results>", pictures, views).read_text()
    assert "<h1>demo &lt;results&gt;</h1>" in page
    for name, r in results.items():
        assert f"<td>{name}</td>" in page
        for metric in ("miou", "iou", "l2_at", "l2_mean"):
            if r[metric]["avg"] is not None:
                assert f"<td class=num>{r[metric]['avg']:.2f}</td>" in page, (name, metric)
    assert page.count("<svg") >= 2 and "mIoU (%)" in page and "IoU (%)" in page
    assert len(re.findall(r"<path d=", page)) == 2 * sum(r["miou"]["1s"] is not None for r in results.values())
    assert '<img src="scene-t00.png"' in page and '<img src="scene-t00.gif"' in page
    assert '<a href="views/scene%200.html">' in page
    assert "<script" not in page and "http" not in page.replace("http://www.w3.org/2000/svg", "")
