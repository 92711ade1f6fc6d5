"""Page loading in headless Chromium (WebGL on the SwiftShader software rasteriser): a demo
window's 3D viewer until it has decoded the labels and drawn its first frame, and the demo's
``index.html`` until every picture has loaded. Wall-clock time of one Chromium run, start-up
included; skipped without Chromium (``make browser``).

Run with ``python -m pytest benchmarks/test_bench_pages.py --benchmark-only``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

# the Chromium helpers live with the browser tests; plain `pytest` puts only benchmarks/ on the path
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.viz.browser import INSTALL_HINT, file_url, find_chromium, page_resources, run_chromium  # noqa: E402

pytestmark = pytest.mark.skipif(find_chromium() is None, reason=INSTALL_HINT)

METRICS = Path(__file__).parent / "results" / "wm-test-metrics.json"


@pytest.fixture(scope="module")
def demo_folder(tmp_path_factory) -> Path:
    """A demo-like folder: one synthetic test window as a 3D page and as pictures (the truth
    as the forecast), and an ``index.html`` showing them."""
    from t3fast.data.synthetic import SyntheticDriving
    from t3fast.viz.bev import save_forecast_pictures
    from t3fast.viz.index_page import write_index
    from t3fast.viz.viewer import write_window_viewer

    folder = tmp_path_factory.mktemp("pages")
    sample = SyntheticDriving("test", 1, stride=8)[0]
    truth, plan = sample.future_occ.numpy(), sample.trajectory.numpy()
    view = write_window_viewer(folder / "window.html", sample, truth, plan, "truth as the forecast")
    pictures = save_forecast_pictures(folder / "window", sample.past_occ.numpy(), truth, truth, plan, plan)
    write_index(folder, json.loads(METRICS.read_text()), "page-load benchmark", list(pictures), [view])
    return folder


def test_window_viewer_load(benchmark, demo_folder):
    benchmark.group = "page load (headless Chromium)"
    url = file_url(demo_folder / "window.html")
    run = benchmark.pedantic(lambda: run_chromium(url, dump_dom=True), rounds=3)
    assert 'data-ready="1"' in run.body_attributes() and run.console_errors() == []


def test_index_page_load(benchmark, demo_folder):
    benchmark.group = "page load (headless Chromium)"
    resources = benchmark.pedantic(lambda: page_resources(demo_folder / "index.html"), rounds=3)
    assert resources["images"] and all(image["width"] > 0 for image in resources["images"])
