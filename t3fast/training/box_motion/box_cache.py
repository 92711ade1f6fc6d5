"""What the box motion network trains on: per window, the scene's context map and, per agent
drawn as a fitted box, its kinematics and its true future motion.

The boxes are fitted once per window (:func:`~t3fast.agents.boxes.fit_agent_boxes`, the
costly part: ~0.5 s a window) and stored with the window's :func:`context_map` (the groups as
bits, the velocities in float16), one entry file per scene of the train split
(:class:`~t3fast.training.cache_files.SceneFiles`: checked when read, fitted again when broken,
written atomically), so fitting is resumable and every run that reads a scene shares its file.
The folder's name (the key) changes with the world's data, the frames per scene, the stride and
the code of the fit and the features.
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

from t3fast.agents import box_kinematics, boxes, tracker
from t3fast.agents.box_kinematics import (
    CONTEXT_CHANNELS,
    CROP,
    agent_headings,
    context_map,
    crop_context,
    ego_step,
    kinematics,
)
from t3fast.agents.boxes import fit_agent_boxes
from t3fast.data.sample import NUM_FUTURE, PRESENT, DrivingSample, collate_samples
from t3fast.data.synthetic import SyntheticDriving
from t3fast.models.ego_motion import planar_poses, wrap_angle
from t3fast.ops import reference
from t3fast.training.cache_files import Field, Layout, Payload, SceneFiles, world_digest
from t3fast.training.gathered import GatheredBatches

MATCH_METRES = 1.0
GROUPS = len(box_kinematics.CONTEXT_GROUPS)
BOX_CACHE_FORMAT = 2  # 2: one checked entry file per scene
#: a record's fields with one row per agent, in the order :class:`BoxMotionSamples` keeps them
AGENT_FIELDS = ("centre", "heading", "velocity", "features", "displacement", "turn", "valid")


def cache_key(windows: SyntheticDriving) -> str:
    """Changes with the windows (the world's data, the split, the frames per scene, the stride)
    and with the code of the fit and the features."""
    code = hashlib.sha256()
    # the fit's definition: the fused op's kernels follow its reference
    fit = (reference.box_fit, reference.box_fit_samples, reference.fit_adam, reference.fit_gradient)
    for source in (tracker, boxes, box_kinematics, *fit):
        code.update(inspect.getsource(source).encode())
    scenes = windows.scenes
    return (f"{world_digest(scenes)}-{scenes.split}-{scenes.frames_per_scene}f-stride{windows.stride}"
            f"-{code.hexdigest()[:12]}-v{BOX_CACHE_FORMAT}")


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


class BoxCache(SceneFiles):
    """The records of the windows of scenes ``scenes`` of a :class:`SyntheticDriving` split,
    in ``cache_dir/box-motion-<key>`` (:func:`cache_key`); a scene's file holds its windows'
    records, the agents of all its windows one after the other (``agents``: how many each has)."""

    kind = "box-motion"

    def __init__(self, windows: SyntheticDriving, cache_dir: str | Path, scenes: range | None = None,
                 desc: str = "box fits"):
        key = cache_key(windows)
        super().__init__(windows, Path(cache_dir) / f"box-motion-{key}", key, scenes)
        self.desc = desc

    def layout(self, scene: int) -> Layout:
        windows = self.windows_of(scene)
        return {"groups": Field(torch.uint8, (windows, GROUPS, "x", "y")),
                "velocity_map": Field(torch.float16, (windows, 2, "x", "y")),
                "agents": Field(torch.int64, (windows,)),
                "centre": Field(torch.float32, ("n", 2)),
                "heading": Field(torch.float32, ("n",)),
                "velocity": Field(torch.float32, ("n", 2)),
                "features": Field(torch.float32, ("n", "features")),
                "displacement": Field(torch.float32, ("n", NUM_FUTURE, 2)),
                "turn": Field(torch.float32, ("n", NUM_FUTURE)),
                "valid": Field(torch.bool, ("n", NUM_FUTURE))}

    def check(self, payload: Payload) -> str | None:
        """The windows' agent counts add up to the agents held; the groups are bits."""
        agents, held = payload["agents"], payload["centre"].shape[0]
        if bool((agents < 0).any()) or int(agents.sum()) != held:
            return f"agent counts {agents.tolist()} do not add up to the {held} agents held"
        if payload["groups"].numel() and int(payload["groups"].max()) > 1:
            return "context groups hold values other than 0 and 1"
        return None

    def build_scene(self, scene: int) -> Payload:
        records = [window_record(sample) for sample in self.scene_windows(scene)]
        return {"groups": torch.stack([r["groups"] for r in records]),
                "velocity_map": torch.stack([r["velocity_map"] for r in records]),
                "agents": torch.tensor([r["centre"].shape[0] for r in records], dtype=torch.int64),
                **{k: torch.cat([r[k] for r in records]) for k in AGENT_FIELDS}}

    def records(self, progress: bool = True) -> list[dict[str, Tensor]]:
        """Every window's :func:`window_record`, in order; fits the scenes missing or broken."""
        self.build(progress)
        out = []
        for part in self.read_scenes():
            agents = part["agents"].tolist()
            by_window = {k: part[k].split(agents) for k in AGENT_FIELDS}
            for w in range(len(agents)):
                out.append({"groups": part["groups"][w], "velocity_map": part["velocity_map"][w],
                            **{k: by_window[k][w] for k in AGENT_FIELDS}})
        return out


class BoxMotionSamples(GatheredBatches):
    """The agents of cached windows, flat, each with its view of its window
    (:func:`~t3fast.agents.box_kinematics.crop_context`, float16) and its :data:`AGENT_FIELDS`,
    held on ``device`` where they fit; a batch is the dict of those fields, ``views``
    ``[n, CONTEXT_CHANNELS, *CROP]`` first."""

    def __init__(self, records: list[dict[str, Tensor]], device: torch.device | str = "cpu"):
        counts = [r["centre"].shape[0] for r in records]
        # filled in place: a list of every window's views and their concatenation would hold
        # them twice (1,620 scenes: 6.7 GB each, beside the records' 4.7 GB of context maps)
        views = torch.empty(sum(counts), CONTEXT_CHANNELS, *CROP, dtype=torch.float16)
        start = 0
        for r, n in zip(records, counts):
            context = torch.cat([r["groups"].float(), r["velocity_map"].float()])
            views[start : start + n] = crop_context(context, r["centre"], r["heading"])
            start += n
        super().__init__({"views": views, **{k: torch.cat([r[k] for r in records]) for k in AGENT_FIELDS}}, device)
