"""The viewer in a real browser: headless Chromium, WebGL on the SwiftShader software rasteriser.

Checks that the page decodes the same labels as Python (per-class counts), draws the
palette colours of the classes seen from above, changes with the frame, shows the same
observed frame on both sides in the past, and logs no errors.
"""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from t3fast.data import classes as C
from t3fast.viz.viewer import write_scene_viewer, write_viewer
from tests.viz.browser import INSTALL_HINT, file_url, find_chromium, run_chromium

pytestmark = pytest.mark.skipif(find_chromium() is None, reason=INSTALL_HINT)

SIZE = (1280, 720)
# the two views (545 px wide each) in a screenshot of SIZE, below the control bar and the view names
LEFT = (slice(64, SIZE[1]), slice(5, 540))
RIGHT = (slice(64, SIZE[1]), slice(550, 1085))
FUTURE_STEP = 10  # the last future frame


@pytest.fixture(scope="module")
def window(synthetic_window, tmp_path_factory):
    """A window page whose prediction is the truth shifted 12 voxels left, with an ignore slab."""
    occ = synthetic_window["occ"]
    predicted = np.roll(occ[5:], 12, axis=2)
    predicted[:, :4] = C.IGNORE
    frames = {"observed": occ[:5], "predicted": predicted, "truth": occ[5:]}
    path = write_viewer(tmp_path_factory.mktemp("viewer") / "window.html", past=occ[:5], predicted=predicted,
                        truth=occ[5:], plan=synthetic_window["trajectory"] * 1.2,
                        true_plan=synthetic_window["trajectory"], masks=synthetic_window["mask"], title="test")
    return path, frames, synthetic_window["mask"]


@pytest.fixture(scope="module")
def runs(window):
    path, _, _ = window
    shots = {step: path.with_name(f"frame{step}.png") for step in (0, FUTURE_STEP)}
    out = {"dom": run_chromium(file_url(path, f"frame={FUTURE_STEP}"), dump_dom=True, size=SIZE)}
    for step, shot in shots.items():
        out[step] = run_chromium(file_url(path, f"frame={step}"), screenshot=shot, size=SIZE)
        out[f"image{step}"] = np.asarray(Image.open(shot).convert("RGB")).astype(np.int16)
    return out


def _palette_fraction(image: np.ndarray, class_id: int, tolerance: int = 3) -> float:
    """Fraction of the pixels of ``image`` ``[H, W, 3]`` within ``tolerance`` of the class's colour."""
    return float((np.abs(image - C.PALETTE[class_id].astype(np.int16)).max(-1) <= tolerance).mean())


def _top_classes(occ: np.ndarray, k: int) -> list[int]:
    """The ``k`` commonest classes of the highest occupied voxel of each column (what a camera above sees)."""
    occupied = (occ != C.FREE) & (occ != C.IGNORE)
    top = occ.shape[2] - 1 - np.argmax(occupied[..., ::-1], axis=2)
    label = np.take_along_axis(occ, top[..., None], axis=2)[..., 0][occupied.any(axis=2)]
    return np.argsort(np.bincount(label, minlength=C.FREE))[::-1][:k].tolist()


def test_page_loads_without_errors(runs):
    for name in ("dom", 0, FUTURE_STEP):
        assert runs[name].console_errors() == [], runs[name].console_errors()
    attributes = runs["dom"].body_attributes()
    assert 'data-ready="1"' in attributes and "data-error" not in attributes, attributes


def test_browser_decode_matches_python_labels(runs, window):
    _, frames, mask = window
    checksums = runs["dom"].checksums()
    ids = checksums["classes"]
    assert ids == [*range(C.FREE + 1), C.IGNORE]
    for name, labels in frames.items():
        expected = [np.bincount(f.ravel(), minlength=256)[ids].tolist() for f in labels]
        assert checksums["sequences"][name] == expected, name
    assert checksums["masks"] == mask.sum(axis=(1, 2, 3)).tolist()


def test_screenshot_shows_the_palette_of_the_visible_classes(runs, window):
    _, frames, _ = window
    view = runs[f"image{FUTURE_STEP}"][RIGHT]
    assert len(np.unique(view.reshape(-1, 3), axis=0)) > 20  # not blank
    top = _top_classes(frames["truth"][FUTURE_STEP - 5], 3)
    fractions = {c: _palette_fraction(view, c) for c in range(C.FREE)}
    assert all(fractions[c] > 0.003 for c in top), (top, fractions)
    assert max(fractions, key=fractions.get) in top, (top, fractions)


def test_frames_and_views_differ_where_they_should(runs):
    past, future = runs["image0"], runs[f"image{FUTURE_STEP}"]
    assert (past[RIGHT] != future[RIGHT]).any(-1).mean() > 0.05  # another frame
    assert (past[LEFT] != past[RIGHT]).any(-1).mean() < 0.01  # the same observed frame on both sides
    assert (future[LEFT] != future[RIGHT]).any(-1).mean() > 0.05  # prediction vs truth


def test_scene_viewer_hides_unseen_voxels(synthetic_window, tmp_path):
    path = write_scene_viewer(tmp_path / "scene.html", synthetic_window["occ"][:3], synthetic_window["mask"][:3])
    run = run_chromium(file_url(path, "frame=2&mask=hide"), dump_dom=True, size=(800, 600))
    assert run.console_errors() == []
    assert 'data-ready="1"' in run.body_attributes()
    counts = run.checksums()["sequences"]["scene"]
    assert [c[C.FREE] for c in counts] == (synthetic_window["occ"][:3] == C.FREE).sum(axis=(1, 2, 3)).tolist()
