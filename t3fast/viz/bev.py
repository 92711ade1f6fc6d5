"""Bird's-eye-view pictures of occupancy: what a person looks at to check the data.

``bev_image`` colours each voxel column by its highest occupied voxel in the
Occ3D palette (``t3fast.data.classes.PALETTE``). Pictures have the ego's
forward direction (+x) pointing up and its left (+y) pointing left.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from t3fast.data import classes as C
from t3fast.data.sample import PRESENT, DrivingSample, box_corners, boxes_to_frame

EMPTY_COLOUR = (40, 40, 40)
UNSEEN_DARKEN = 0.45
EGO_COLOUR = (0, 255, 0)
BOX_COLOUR = (255, 255, 255)
PLAN_COLOUR = (0, 255, 0)
TRUE_COLOUR = (0, 200, 255)
TEXT_COLOUR = (0, 0, 0)


def bev_colours(occ: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """RGB uint8 ``[X, Y, 3]`` (array layout, x down the rows) of a label volume ``[X, Y, Z]``.

    Each column takes the colour of its highest voxel that is neither free nor
    ignore; empty columns are dark grey. With ``mask`` (bool ``[X, Y, Z]``),
    columns whose top voxel is not visible are darkened.
    """
    occupied = (occ != C.FREE) & (occ != C.IGNORE)
    any_occ = occupied.any(axis=2)
    top = occ.shape[2] - 1 - np.argmax(occupied[..., ::-1], axis=2)
    label = np.take_along_axis(occ, top[..., None], axis=2)[..., 0]
    rgb = np.where(any_occ[..., None], C.PALETTE[np.where(any_occ, label, 0)], np.array(EMPTY_COLOUR, np.uint8))
    if mask is not None:
        seen = np.take_along_axis(mask, top[..., None], axis=2)[..., 0]
        rgb = np.where(seen[..., None] | ~any_occ[..., None], rgb, (rgb * UNSEEN_DARKEN).astype(np.uint8))
    return rgb.astype(np.uint8)


def _to_pixels(xy: np.ndarray, scale: int) -> np.ndarray:
    """Ego-frame metres ``[..., 2]`` -> image (column, row) pixels, forward up, left left."""
    col = (C.GRID_UPPER[1] - xy[..., 1]) / C.VOXEL_SIZE * scale
    row = (C.GRID_UPPER[0] - xy[..., 0]) / C.VOXEL_SIZE * scale
    return np.stack([col, row], -1)


def bev_image(
    occ: np.ndarray,
    boxes: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    trajectory: np.ndarray | None = None,
    scale: int = 2,
    true_trajectory: np.ndarray | None = None,
    more_paths: Sequence[tuple[np.ndarray, tuple[int, int, int]]] = (),
) -> Image.Image:
    """Top-down picture of one frame.

    occ: label volume ``[200, 200, 16]``; boxes: ``[N, 7]`` in this frame's ego
    coordinates (outlined); mask: optional visibility ``[200, 200, 16]``;
    trajectory: optional ego positions ``[K, 2]`` (drawn as a green polyline from the ego);
    true_trajectory: another one drawn in cyan underneath (e.g. the ground truth next to a
    plan); more_paths: further ``(positions [K, 2], RGB colour)`` drawn between the two. The
    ego (nuScenes footprint) is drawn at the origin.
    """
    rgb = bev_colours(np.asarray(occ), None if mask is None else np.asarray(mask))
    # array [x, y] -> image [row, col] with x up and y left
    img = np.ascontiguousarray(rgb[::-1, ::-1])
    image = Image.fromarray(img).resize((img.shape[1] * scale, img.shape[0] * scale), Image.NEAREST)
    draw = ImageDraw.Draw(image)
    if boxes is not None and len(boxes):
        for corners in _to_pixels(box_corners(np.asarray(boxes, dtype=np.float64)), scale):
            draw.polygon([tuple(p) for p in corners], outline=BOX_COLOUR)
    ego = np.array([[0, 0, 0, C.EGO_LENGTH, C.EGO_WIDTH, 1.5, 0.0]])
    draw.polygon([tuple(p) for p in _to_pixels(box_corners(ego)[0], scale)], outline=EGO_COLOUR, fill=EGO_COLOUR)
    for path, colour in ((true_trajectory, TRUE_COLOUR), *more_paths, (trajectory, PLAN_COLOUR)):
        if path is not None and len(path):
            pts = _to_pixels(np.concatenate([np.zeros((1, 2)), np.asarray(path, dtype=np.float64)]), scale)
            draw.line([tuple(p) for p in pts], fill=colour, width=max(scale, 1))
    return image


def sample_frame_boxes(sample: DrivingSample, t: int) -> np.ndarray:
    """The valid boxes of frame ``t`` moved from the present frame into frame ``t``'s own ego frame."""
    poses = sample.ego_poses.double().numpy()
    to_t = np.linalg.inv(poses[t]) @ poses[PRESENT]
    valid = sample.box_valid[t].numpy()
    return boxes_to_frame(sample.boxes[t].double().numpy()[valid], to_t)


def render_sample(sample: DrivingSample, frames: list[int] | None = None, scale: int = 1,
                  show_mask: bool = False) -> Image.Image:
    """A strip of BEV pictures of ``frames`` (default: every frame) of a sample, left to right.

    Each frame shows its own boxes; the present frame also shows the future
    trajectory (cumulated future actions).
    """
    frames = list(range(sample.occ.shape[0])) if frames is None else frames
    tiles = []
    for t in frames:
        mask = sample.mask_camera[t].numpy() if show_mask else None
        plan = sample.trajectory.numpy() if t == PRESENT else None
        tiles.append(bev_image(sample.occ[t].numpy(), sample_frame_boxes(sample, t), mask, plan, scale))
    gap = 4
    width = sum(t.width for t in tiles) + gap * (len(tiles) - 1)
    strip = Image.new("RGB", (width, tiles[0].height), (255, 255, 255))
    x = 0
    for tile in tiles:
        strip.paste(tile, (x, 0))
        x += tile.width + gap
    return strip


def save_sample_png(sample: DrivingSample, path: str | Path, frames: list[int] | None = None, scale: int = 1,
                    show_mask: bool = False) -> Path:
    """Render ``render_sample`` to a PNG file; returns its path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    render_sample(sample, frames, scale, show_mask).save(path, optimize=True)
    return path


def _captioned(tile: Image.Image, caption: str) -> Image.Image:
    out = Image.new("RGB", (tile.width, tile.height + 14), (255, 255, 255))
    out.paste(tile, (0, 14))
    ImageDraw.Draw(out).text((2, 1), caption, fill=TEXT_COLOUR)
    return out


def _grid(rows: list[list[Image.Image]], gap: int = 4) -> Image.Image:
    width = max(sum(t.width for t in row) + gap * (len(row) - 1) for row in rows)
    height = sum(max(t.height for t in row) for row in rows) + gap * (len(rows) - 1)
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    y = 0
    for row in rows:
        x = 0
        for tile in row:
            canvas.paste(tile, (x, y))
            x += tile.width + gap
        y += max(t.height for t in row) + gap
    return canvas


def forecast_figure(
    past: np.ndarray, predicted: np.ndarray, truth: np.ndarray, planned: np.ndarray, true_path: np.ndarray,
    scale: int = 1, name: str = "T3Former",
) -> Image.Image:
    """Past / predicted / ground-truth BEV frames of one forecast, as three rows.

    past: labels ``[5, X, Y, Z]`` (the present last); predicted, truth: ``[6, X, Y, Z]``;
    planned, true_path: ego positions ``[6, 2]`` in the present frame, drawn on the present
    frame (green: plan, cyan: ground truth). Frames are 0.5 s apart.
    """
    n_past = len(past)
    row_past = [
        _captioned(bev_image(past[t], scale=scale, trajectory=planned if t == n_past - 1 else None,
                             true_trajectory=true_path if t == n_past - 1 else None),
                   f"past {0.5 * (t - n_past + 1):+.1f} s" if t < n_past - 1 else "present + plans")
        for t in range(n_past)
    ]
    row_pred = [_captioned(bev_image(f, scale=scale), f"{name} +{0.5 * (k + 1):.1f} s")
                for k, f in enumerate(predicted)]
    row_true = [_captioned(bev_image(f, scale=scale), f"truth +{0.5 * (k + 1):.1f} s") for k, f in enumerate(truth)]
    return _grid([row_past, row_pred, row_true])


def comparison_figure(present: np.ndarray, rows: list[tuple[str, np.ndarray]], steps: list[int],
                      scale: int = 2) -> Image.Image:
    """The present frame ``[X, Y, Z]`` above one row per method: ``rows`` of (name, future frames
    ``[S, X, Y, Z]``), each drawn at the future ``steps`` (0-based, 0.5 s apart)."""
    top = [_captioned(bev_image(present, scale=scale), "present")]
    grid = [[_captioned(bev_image(frames[k], scale=scale), f"{name} +{0.5 * (k + 1):.1f} s") for k in steps]
            for name, frames in rows]
    return _grid([top, *grid])


def forecast_animation(
    past: np.ndarray, predicted: np.ndarray, truth: np.ndarray, planned: np.ndarray, true_path: np.ndarray,
    scale: int = 2, name: str = "T3Former",
) -> list[Image.Image]:
    """GIF frames of one forecast: the past frames, then predicted next to ground truth per
    future step; the present frame shows the planned (green) and true (cyan) trajectories."""
    frames = []
    for t, occ in enumerate(past):
        present = t == len(past) - 1
        tile = bev_image(occ, scale=scale, trajectory=planned if present else None,
                         true_trajectory=true_path if present else None)
        label = "present" if present else f"past {0.5 * (t - len(past) + 1):+.1f} s"
        frames.append(_grid([[_captioned(tile, label), _captioned(tile, label)]]))
    for k, (p, g) in enumerate(zip(predicted, truth)):
        when = f"+{0.5 * (k + 1):.1f} s"
        frames.append(_grid([[_captioned(bev_image(p, scale=scale), f"{name} {when}"),
                              _captioned(bev_image(g, scale=scale), f"truth {when}")]]))
    return frames


def save_forecast_pictures(
    path: str | Path, past: np.ndarray, predicted: np.ndarray, truth: np.ndarray, planned: np.ndarray,
    true_path: np.ndarray, name: str = "T3Former",
) -> tuple[Path, Path]:
    """Write ``path.png`` (:func:`forecast_figure`) and ``path.gif`` (:func:`forecast_animation`,
    2 frames per second, looping); returns both paths."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    png, gif = path.with_suffix(".png"), path.with_suffix(".gif")
    forecast_figure(past, predicted, truth, planned, true_path, name=name).save(png, optimize=True)
    frames = forecast_animation(past, predicted, truth, planned, true_path, name=name)
    frames[0].save(gif, save_all=True, append_images=frames[1:], duration=500, loop=0, optimize=True)
    return png, gif
