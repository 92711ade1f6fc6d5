"""Self-contained HTML pages that show occupancy in 3D (three.js, WebGL).

A page is one file that works offline from a ``file://`` URL: three.js, the viewer code
(``static/viewer.js``) and the labels (packed by :mod:`t3fast.viz.voxel_pack`) are all
inline. It draws every occupied voxel (not free, not ignore) as a cube in the Occ3D
palette, with a time slider, a play button, a legend, the ego as a box and trajectories
as ribbons on the ground; cameras of side-by-side views are linked.

:func:`write_viewer` shows a forecast window: past frames, then the predicted future next
to the ground truth. :func:`write_scene_viewer` shows one sequence of frames.

Every frame is shown in its own ego frame (each future frame's labels are in that frame's
ego coordinates), so the ego box stays at the origin; the trajectories are in the present
frame's coordinates and drawn as given on every frame.

The URL hash sets the state, e.g. ``page.html#frame=7&mask=dark`` (``mask``: ``show``,
``dark`` or ``hide`` voxels outside the camera visibility mask).
"""

from __future__ import annotations

import functools
import html
import json
import re
from pathlib import Path

import numpy as np

from t3fast.data import classes as C
from t3fast.data.sample import DrivingSample
from t3fast.errors import DataFormatError
from t3fast.viz.bev import EGO_COLOUR, PLAN_COLOUR, TRUE_COLOUR
from t3fast.viz.voxel_pack import check_labels, check_masks, pack_frames, pack_masks, unpack_frames, unpack_masks

STATIC = Path(__file__).with_name("static")
EGO_HEIGHT = 1.5
#: initial camera: behind the ego and above it, looking at a point ahead of it
CAMERA = {"target": [4.0, 0.0, 0.0], "azimuth": 0.0, "elevation": 0.72, "distance": 110.0}

_DATA_RE = re.compile(r'<script type="application/json" id="t3-data">(.*?)</script>', re.S)

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>
{css}
</style>
</head>
<body>
<div id="t3-app"></div>
<pre id="t3-error" hidden></pre>
<pre id="t3-checksums" hidden></pre>
<script type="application/json" id="t3-data">{data}</script>
<script type="module">
{three}
{viewer}
</script>
</body>
</html>
"""


@functools.lru_cache(maxsize=1)
def _three_script() -> str:
    """three.js as a statement defining ``const THREE``: the module's final ``export{a as B, ...}``
    becomes the returned object of a function, so the viewer code can follow it in one script."""
    source = (STATIC / "three.module.min.js").read_text(encoding="utf-8")
    match = re.search(r"export\{([^}]*)\};?\s*$", source)
    if match is None or re.search(r"(?:^|[;}\n])\s*import[\s{*\"']", source):
        raise RuntimeError("three.module.min.js: expected a standalone module ending in export{...}")
    entries = []
    for item in match.group(1).split(","):
        local, _, exported = item.strip().partition(" as ")
        entries.append(f"{exported or local}:{local}")
    return "const THREE = (() => {\n" + source[: match.start()] + "\nreturn {" + ",".join(entries) + "};\n})();"


def _trajectory(points: object, name: str) -> list[list[float]]:
    """Ego positions ``[K, 2]`` (metres) as a list, or a DataFormatError naming ``name``."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise DataFormatError(f"{name}: expected shape (K, 2) ego positions in metres, got {tuple(arr.shape)}")
    if not np.isfinite(arr).all():
        raise DataFormatError(f"{name}: positions must be finite")
    return np.round(arr, 3).tolist()


def _write_page(path: str | Path, title: str, sequences: dict[str, np.ndarray], views: list[dict],
                steps: list[str], masks: np.ndarray | None, trajectories: list[dict], frame_dt: float) -> Path:
    """Write the page; ``views[i]["frames"][t]`` is the ``[sequence name, index]`` view i shows at step t."""
    data = {
        "title": title,
        "frameDt": frame_dt,
        "grid": {"shape": list(C.GRID_SHAPE), "lower": list(C.GRID_LOWER), "voxel": C.VOXEL_SIZE},
        "palette": C.PALETTE.tolist(),
        "classNames": list(C.CLASS_NAMES),
        "free": C.FREE,
        "ignore": C.IGNORE,
        "ego": {"length": C.EGO_LENGTH, "width": C.EGO_WIDTH, "height": EGO_HEIGHT, "color": list(EGO_COLOUR)},
        "camera": CAMERA,
        "sequences": {name: pack_frames(frames) for name, frames in sequences.items()},
        "masks": None if masks is None else pack_masks(masks),
        "views": views,
        "steps": steps,
        "trajectories": trajectories,
    }
    page = _PAGE.format(
        title=html.escape(title or "occupancy"),
        css=(STATIC / "viewer.css").read_text(encoding="utf-8"),
        data=json.dumps(data, separators=(",", ":")).replace("<", "\\u003c"),  # no "</script>" inside
        three=_three_script(),
        viewer=(STATIC / "viewer.js").read_text(encoding="utf-8"),
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(page, encoding="utf-8")
    return path


def write_viewer(
    path: str | Path,
    *,
    past: np.ndarray,
    predicted: np.ndarray | None = None,
    truth: np.ndarray | None = None,
    plan: np.ndarray | None = None,
    true_plan: np.ndarray | None = None,
    masks: np.ndarray | None = None,
    title: str = "",
    prediction_name: str = "prediction",
    frame_dt: float = C.FRAME_DT,
) -> Path:
    """Write a 3D view of one forecast window to ``path`` (HTML); returns the path.

    past: labels uint8 ``[P, 200, 200, 16]``, the present last; predicted, truth: the future
    ``[F, 200, 200, 16]`` (either or both). With both, two linked views: ``prediction_name``
    and "ground truth"; the past steps show the same observed frame on both sides. plan
    (green), true_plan (cyan): ego positions ``[K, 2]`` in the present frame. masks: camera
    visibility bool ``[P + F, 200, 200, 16]`` of the timeline's steps (applied to every view).
    Frames are ``frame_dt`` seconds apart.
    """
    past = check_labels(past, "past")
    future = {name: check_labels(arr, arg) for name, arr, arg in
              (("predicted", predicted, "predicted"), ("truth", truth, "truth")) if arr is not None}
    lengths = {len(arr) for arr in future.values()}
    if len(lengths) > 1:
        raise DataFormatError(f"predicted and truth: expected the same number of frames, got "
                              f"{len(future['predicted'])} and {len(future['truth'])}")
    n_future = lengths.pop() if lengths else 0
    n_past = len(past)
    steps = [("present" if t == n_past - 1 else f"past {(t - n_past + 1) * frame_dt:+.1f} s") for t in range(n_past)]
    steps += [f"future +{(k + 1) * frame_dt:.1f} s" for k in range(n_future)]
    if masks is not None:
        masks = check_masks(masks, "masks")
        if len(masks) != len(steps):
            raise DataFormatError(f"masks: expected {len(steps)} frames (past + future), got {len(masks)}")
    observed = [["observed", t] for t in range(n_past)]
    titles = {"predicted": prediction_name, "truth": "ground truth"}
    views = [{"name": titles[name], "frames": observed + [[name, k] for k in range(n_future)]} for name in future]
    trajectories = [{"name": name, "color": list(colour), "points": _trajectory(points, arg)}
                    for name, colour, points, arg in (("true trajectory", TRUE_COLOUR, true_plan, "true_plan"),
                                                      ("plan", PLAN_COLOUR, plan, "plan"))
                    if points is not None]
    return _write_page(path, title, {"observed": past, **future}, views or [{"name": "observed", "frames": observed}],
                       steps, masks, trajectories, frame_dt)


def write_scene_viewer(
    path: str | Path, frames: np.ndarray, masks: np.ndarray | None = None, title: str = "",
    frame_dt: float = C.FRAME_DT,
) -> Path:
    """Write a 3D view of one sequence, labels uint8 ``[T, 200, 200, 16]`` (optional visibility
    masks bool ``[T, 200, 200, 16]``), to ``path`` (HTML); returns the path."""
    frames = check_labels(frames, "frames")
    if masks is not None:
        masks = check_masks(masks, "masks")
        if len(masks) != len(frames):
            raise DataFormatError(f"masks: expected {len(frames)} frames like frames, got {len(masks)}")
    steps = [f"frame {t} ({t * frame_dt:.1f} s)" for t in range(len(frames))]
    views = [{"name": "scene", "frames": [["scene", t] for t in range(len(frames))]}]
    return _write_page(path, title, {"scene": frames}, views, steps, masks, [], frame_dt)


def read_viewer_data(path: str | Path) -> dict:
    """The data embedded in a viewer page, decoded: the JSON object with ``"sequences"``
    (name -> labels uint8 ``[T, 200, 200, 16]``) and ``"masks"`` (bool or None) unpacked."""
    match = _DATA_RE.search(Path(path).read_text(encoding="utf-8"))
    if match is None:
        raise DataFormatError(f"{path}: not a t3fast viewer page (no t3-data script)")
    data = json.loads(match.group(1))
    data["sequences"] = {name: unpack_frames(text) for name, text in data["sequences"].items()}
    data["masks"] = None if data["masks"] is None else unpack_masks(data["masks"])
    return data


def write_window_viewer(
    path: str | Path, sample: DrivingSample, predicted: np.ndarray | None = None, plan: np.ndarray | None = None,
    title: str = "", prediction_name: str = "T3Former",
) -> Path:
    """A 3D view of an 11-frame window (:class:`~t3fast.data.sample.DrivingSample`): its frames
    alone, or with ``predicted`` labels ``[6, 200, 200, 16]`` and the planned positions ``plan``
    ``[6, 2]``, the forecast next to the ground truth with the true trajectory; the window's
    visibility masks are the mask option."""
    masks = sample.mask_camera.numpy()
    if predicted is None:
        return write_scene_viewer(path, sample.occ.numpy(), masks, title)
    return write_viewer(path, past=sample.past_occ.numpy(), predicted=predicted, truth=sample.future_occ.numpy(),
                        plan=plan, true_plan=sample.trajectory.numpy(), masks=masks, title=title,
                        prediction_name=prediction_name)
