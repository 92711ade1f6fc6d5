"""The demo's index.html: metrics table, per-horizon SVG curves, pictures and 3D view links."""

from __future__ import annotations

import json
import re
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

from t3fast.commands.main import main
from t3fast.viz.index_page import write_index
from tests.viz.browser import INSTALL_HINT, find_chromium, page_resources

METRICS = Path(__file__).parents[2] / "benchmarks" / "results" / "wm-test-metrics.json"


def _results() -> dict[str, dict]:
    results = json.loads(METRICS.read_text())
    results["copy_paste"]["miou"]["2s"] = None  # a gap in a curve
    return results


def test_index_has_table_curves_pictures_and_views(tmp_path):
    results = _results()
    pictures = [tmp_path / "scene-t00.png", tmp_path / "scene-t00.gif"]
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


def _linked_paths(page: Path) -> list[Path]:
    """The files the ``src`` and ``href`` attributes of ``page`` point to, resolved as a browser does."""
    urls = re.findall(r'(?:src|href)="([^"]+)"', page.read_text())
    return [(page.parent / unquote(urlsplit(url).path)).resolve() for url in urls]


@pytest.mark.parametrize("out", ["demo", "./runs/../demo", "absolute"])
def test_links_are_relative_to_the_page_whatever_the_out_folder(tmp_path, monkeypatch, out):
    monkeypatch.chdir(tmp_path)
    out_dir = tmp_path / "demo" if out == "absolute" else Path(out)
    (tmp_path / "runs").mkdir()
    # as the writers return them: under the output folder, spelled the way the user gave it
    files = [out_dir / "pictures" / name for name in ("scene-t00.png", "scene-t00.gif", "scene 0.html")]
    for path in files:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
    page = write_index(out_dir, _results(), "demo", files[:2], files[2:])
    assert page.resolve() == (tmp_path / "demo" / "index.html")
    text = page.read_text()
    assert '<img src="pictures/scene-t00.png"' in text and '<img src="pictures/scene-t00.gif"' in text
    assert '<a href="pictures/scene%200.html">' in text
    assert _linked_paths(page) == [(tmp_path / "demo" / "pictures" / f.name) for f in files[2:] + files[:2]]


@pytest.mark.slow
@pytest.mark.skipif(find_chromium() is None, reason=INSTALL_HINT)
def test_demo_page_shows_every_picture_and_links_existing_views(tmp_path, monkeypatch):
    """The index.html that ``t3fast demo --out demo`` writes (relative folder, as ``make demo``
    passes it), in the browser; the demo's smallest setting: one scene, one window, one picture."""
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--out", "demo", "--scenes", "1", "--stride", "64", "--pictures", "1"]) == 0
    written = sorted((tmp_path / "demo" / "pictures").iterdir())
    resources = page_resources(tmp_path / "demo" / "index.html")
    images = {_file(image["src"]): image["width"] for image in resources["images"]}
    assert sorted(images) == [p for p in written if p.suffix in (".png", ".gif")]
    assert all(width > 0 for width in images.values()), images
    links = [_file(url) for url in resources["links"]]
    assert links == [p for p in written if p.suffix == ".html"] and all(p.is_file() for p in links)


def _file(url: str) -> Path:
    """The local path of a ``file://`` URL."""
    parts = urlsplit(url)
    assert parts.scheme == "file", url
    return Path(unquote(parts.path))
