"""What the box motion network trains on: per window, the scene's context map and, per agent
drawn as a fitted box, its kinematics and its true future motion.

The boxes are fitted once per window (:func:`~t3fast.models.agent_boxes.fit_agent_boxes`, the
costly part: ~0.5 s a window) and stored with the window's :func:`context_map` (the groups as
bits, the velocities in float16) in one file, rebuilt when the data or the fit changes (its key).
A fitted agent takes the true box whose present centre is nearest its own, within
``MATCH_METRES``; the true box's displacement and yaw change at every future step where it is
annotated are the targets.
"""

from __future__ import annotations

import hashlib
import inspect
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import Dataset
from tqdm import tqdm

from t3fast.data.sample import PRESENT, DrivingSample, collate_samples
from t3fast.models import agent_boxes, box_motion
from t3fast.models.agent_boxes import fit_agent_boxes
from t3fast.models.box_motion import agent_headings, context_map, crop_context, ego_step, kinematics
from t3fast.models.ego_motion import planar_poses, wrap_angle

MATCH_METRES = 1.0
GROUPS = len(box_motion.CONTEXT_GROUPS)


def cache_key(dataset_name: str, indices: list[int]) -> str:
    """Changes with the windows and with the code of the fit and the features."""
    digest = hashlib.sha256(dataset_name.encode())
    digest.update(repr(indices).encode())
    for module in (agent_boxes, box_motion):
        digest.update(inspect.getsource(module).encode())
    return digest.hexdigest()[:16]


def window_record(sample: DrivingSample) -> dict[str, Tensor]:
    """One window's record: its :func:`context_map` as ``groups`` (uint8 ``[G, X, Y]``) and
    ``velocity_map`` (float16 ``[2, X, Y]``), and per drawn agent with a true box: ``centre``
    ``[n, 2]``, ``heading``,
    ``velocity`` ``[n, 2]``, ``features`` ``[n, F]``, the true ``displacement`` ``[n, S, 2]``
    (present frame, metres), ``turn`` ``[n, S]`` and ``valid`` ``[n, S]``."""
    batch = collate_samples([sample])
    poses = planar_poses(batch.ego_poses, PRESENT).double()[0]
    now, fit = fit_agent_boxes(batch.past_occ[0], poses[: PRESENT + 1])
    context = context_map(batch.past_occ[0, -1], fit, now["ids"], ego_step(poses[: PRESENT + 1]))
    boxes, valid = batch.boxes[0].double(), batch.box_valid[0]
    drawn = fit.drawn.nonzero().flatten()
    dist = (fit.centre[drawn, None] - boxes[PRESENT, None, :, :2]).norm(dim=-1)
    dist[:, ~valid[PRESENT]] = float("inf")
    if dist.shape[1]:
        near, owner = dist.min(1)
    else:  # no annotated box: nobody has a target
        near, owner = dist.new_full((len(drawn),), float("inf")), torch.zeros_like(drawn)
    keep = near <= MATCH_METRES
    agents, owner = drawn[keep], owner[keep]
    heading = agent_headings(fit)
    future = boxes[PRESENT + 1 :, owner]  # [S, m, 7]
    return {
        "groups": (context[:GROUPS] > 0).to(torch.uint8),
        "velocity_map": context[GROUPS:].half(),
        "centre": fit.centre[agents].float(),
        "heading": heading[agents].float(),
        "velocity": fit.velocity[agents].float(),
        "features": kinematics(fit, heading)[agents],
        "displacement": (future[..., :2] - boxes[PRESENT, owner, :2]).transpose(0, 1).float(),
        "turn": wrap_angle(future[..., 6] - boxes[PRESENT, owner, 6]).T.float(),
        "valid": valid[PRESENT + 1 :, owner].T,
    }


def build_records(dataset, indices: list[int], path: Path, desc: str = "box fits") -> list[dict[str, Tensor]]:
    """The records of ``dataset``'s windows ``indices``, loaded from ``path`` when its key
    matches, else built (with a progress bar) and saved there atomically."""
    key = cache_key(f"{type(dataset).__name__}:{getattr(dataset, 'name', '')}:{len(dataset)}", indices)
    if path.exists():
        stored = torch.load(path, weights_only=True)
        if stored.get("key") == key:
            return stored["records"]
    records = [window_record(dataset[i]) for i in tqdm(indices, desc=desc, mininterval=10)]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save({"key": key, "records": records}, tmp)
    tmp.replace(path)
    return records


class BoxMotionSamples(Dataset):
    """The agents of cached windows, flat, each with its view of its window
    (:func:`~t3fast.models.box_motion.crop_context`, float16)."""

    def __init__(self, records: list[dict[str, Tensor]]):
        views = []
        for r in records:
            context = torch.cat([r["groups"].float(), r["velocity_map"].float()])
            views.append(crop_context(context, r["centre"], r["heading"]).half())
        self.views = torch.cat(views)
        self.fields = {k: torch.cat([r[k] for r in records]) for k in
                       ("centre", "heading", "velocity", "features", "displacement", "turn", "valid")}

    def __len__(self) -> int:
        return self.views.shape[0]

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        return self.__getitems__([index])[0]

    def __getitems__(self, indices: list[int]) -> list[dict[str, Tensor]]:
        """The agents ``indices`` one by one (what ``__getitem__`` gives), gathered at once: the
        DataLoader fetches a whole batch through this."""
        index = torch.as_tensor(indices)
        batch = {"views": self.views[index], **{k: v[index] for k, v in self.fields.items()}}
        return [{k: v[i] for k, v in batch.items()} for i in range(len(indices))]
