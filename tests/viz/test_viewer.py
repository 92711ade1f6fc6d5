"""Viewer pages: self-contained, the embedded data decodes to the frames written, bad input is refused."""

from __future__ import annotations

import numpy as np
import pytest

from t3fast.data import classes as C
from t3fast.errors import DataFormatError
from t3fast.viz.viewer import read_viewer_data, write_scene_viewer, write_viewer

MAX_WINDOW_BYTES = 5_000_000


def test_window_page_embeds_the_frames_exactly(synthetic_window, tmp_path):
    occ, mask = synthetic_window["occ"], synthetic_window["mask"]
    predicted = occ[5:].copy()
    predicted[:, :3] = C.IGNORE
    path = write_viewer(tmp_path / "w.html", past=occ[:5], predicted=predicted, truth=occ[5:],
                        plan=synthetic_window["trajectory"], true_plan=synthetic_window["trajectory"],
                        masks=mask, title="a <window>", prediction_name="T3Former")
    page = path.read_text()
    assert "<script src" not in page and "<link" not in page  # nothing fetched at view time
    assert "<title>a &lt;window&gt;</title>" in page
    assert path.stat().st_size < MAX_WINDOW_BYTES
    data = read_viewer_data(path)
    for name, frames in (("observed", occ[:5]), ("predicted", predicted), ("truth", occ[5:])):
        np.testing.assert_array_equal(data["sequences"][name], frames)
    np.testing.assert_array_equal(data["masks"], mask)
    assert [v["name"] for v in data["views"]] == ["T3Former", "ground truth"]
    assert data["views"][0]["frames"][4] == data["views"][1]["frames"][4] == ["observed", 4]
    assert data["views"][0]["frames"][5] == ["predicted", 0] and data["views"][1]["frames"][5] == ["truth", 0]
    assert len(data["steps"]) == 11 and data["steps"][4] == "present"


def test_scene_page_has_one_view(synthetic_window, tmp_path):
    occ = synthetic_window["occ"][:3]
    data = read_viewer_data(write_scene_viewer(tmp_path / "s.html", occ, title="scene"))
    assert [v["name"] for v in data["views"]] == ["scene"] and data["masks"] is None
    np.testing.assert_array_equal(data["sequences"]["scene"], occ)


def test_bad_inputs_name_the_argument(tmp_path):
    frames = np.full((5, *C.GRID_SHAPE), C.FREE, np.uint8)
    future = frames[:2]
    with pytest.raises(DataFormatError, match="past: expected dtype uint8, got float32"):
        write_viewer(tmp_path / "a.html", past=frames.astype(np.float32))
    with pytest.raises(DataFormatError, match="predicted and truth: expected the same number of frames, got 2 and 1"):
        write_viewer(tmp_path / "a.html", past=frames, predicted=future, truth=future[:1])
    with pytest.raises(DataFormatError, match=r"masks: expected 7 frames \(past \+ future\), got 5"):
        write_viewer(tmp_path / "a.html", past=frames, truth=future, masks=np.ones(frames.shape, bool))
    with pytest.raises(DataFormatError, match=r"plan: expected shape \(K, 2\).*got \(6,\)"):
        write_viewer(tmp_path / "a.html", past=frames, plan=np.zeros(6))
    with pytest.raises(DataFormatError, match="frames: labels must be 0..17 or 255, got \\[20\\]"):
        write_scene_viewer(tmp_path / "a.html", frames + 3)
    assert not (tmp_path / "a.html").exists()
