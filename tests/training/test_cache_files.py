"""Every training cache (route planner, motion head, box motion, aligned latents, triplanes)
reads back only files that say they hold what is asked for: a broken or foreign file is named
in a warning and built again, so a rerun works; building is resumable; every setting that
changes what is cached is in the cache's key."""

from __future__ import annotations

import logging
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from torch import Tensor

from t3fast.data.synthetic import SyntheticDriving, SyntheticScenes
from t3fast.errors import ConfigError
from t3fast.pretrained import load_world_model
from t3fast.training.box_motion import box_cache
from t3fast.training.box_motion.task import BoxMotionTask
from t3fast.training.configs import BoxDataConfig, BoxMotionConfig
from t3fast.training.motion.motion_cache import MotionCache
from t3fast.training.planner.plan_cache import PlanCache
from t3fast.training.triplane_cache import cached_scene_triplanes
from t3fast.training.world_model.latent_cache import AlignedLatentCache, collate_aligned

CACHE_LOGGER = "t3fast"


@pytest.fixture(scope="module")
def model(world_ckpt):
    return load_world_model(world_ckpt)


def _plan(model, root: Path, split: str, frames: int, stride: int) -> list[Tensor]:
    cache = PlanCache(SyntheticDriving(split, 1, frames, stride=stride), model, root)
    cache.build(progress=False)
    batch = cache.all()
    return [batch.present, batch.previous, batch.past_actions, batch.future_actions, batch.command]


def _motion(model, root: Path, split: str, frames: int, stride: int) -> list[Tensor]:
    cache = MotionCache(SyntheticDriving(split, 1, frames, stride=stride), model, root)
    cache.build(progress=False)
    batch = cache.all()
    t = batch.targets
    return [batch.present, batch.previous, batch.velocity, t.cells, t.visible, t.motion]


def _latent(model, root: Path, split: str, frames: int, stride: int) -> list[Tensor]:
    cache = AlignedLatentCache(SyntheticDriving(split, 1, frames, stride=stride), model, root)
    cache.build(progress=False)
    batch = collate_aligned([cache[i] for i in range(len(cache))])
    return [*(p for p in batch.planes if p is not None), batch.boxes, batch.box_valid, batch.past_actions,
            batch.future_actions, batch.velocity]


def _triplanes(model, root: Path, split: str, frames: int, stride: int) -> list[Tensor]:
    planes = cached_scene_triplanes(model.encoder, SyntheticScenes(split, 1, frames), root, progress=False)
    return [p for scene in planes for p in scene if p is not None]


def _box_config(world_ckpt, root: Path, frames: int = 11, stride: int = 1, scenes: int = 2) -> BoxMotionConfig:
    data = BoxDataConfig(train_scenes=scenes, select_scenes=1, frames_per_scene=frames, stride=stride,
                         cache_dir=str(root))
    return BoxMotionConfig(world_model=str(world_ckpt), data=data)


def _box_samples(cfg: BoxMotionConfig) -> list[Tensor]:
    """The training agents' fields the box motion task reads (fitted, or read from the cache)."""
    task = BoxMotionTask(cfg)
    task.build_model()  # the agents are held on its device
    return list(task.train_dataset().fields.values())


@dataclass
class Case:
    """A cache: how a task builds and reads it, the prefix of its folder or file in the cache
    folder, and which file holds another entry of the same kind (another split's, or another
    scene's or window's)."""

    load: Callable[..., list[Tensor]]
    prefix: str
    other_split: str | None  # None: the other entry is the split's second file


CASES = {
    "plan": Case(_plan, "plan-", "val"),
    "motion": Case(_motion, "motion-", "val"),
    "latent": Case(_latent, "aligned-", None),
    "triplanes": Case(_triplanes, "triplanes-", "val"),
    "box": Case(None, "box-", None),
}


def _load(name: str, model, world_ckpt, root: Path, split: str = "train", frames: int | None = None,
          stride: int = 1) -> list[Tensor]:
    """What the cache ``name`` in ``root`` reads back, built where needed (by default: two
    windows of one scene, or for box motion, one window of each of two scenes)."""
    if name == "box":
        return _box_samples(_box_config(world_ckpt, root, frames or 11, stride))
    return CASES[name].load(model, root, split, frames or 12, stride)


def _files(root: Path, name: str, split: str = "train") -> list[Path]:
    """The cache's files of ``split``, in order (the first is the one the tests break)."""
    relative = [(str(p.relative_to(root)), p) for p in root.rglob("*.pt")]
    return sorted(p for r, p in relative if r.startswith(CASES[name].prefix) and re.search(f"[-/]{split}-", r))


@pytest.fixture(scope="module")
def built(model, world_ckpt, tmp_path_factory):
    """Per cache, a folder holding it built (both splits where the other entry is the other
    split's) and what it reads back."""
    out = {}
    for name, case in CASES.items():
        root = tmp_path_factory.mktemp(f"cache-{name}")
        data = _load(name, model, world_ckpt, root)
        if case.other_split:
            _load(name, model, world_ckpt, root, split=case.other_split)
        out[name] = (root, data)
    return out


def _assert_same(a: list[Tensor], b: list[Tensor]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.dtype == y.dtype and torch.equal(x, y)


# ---------------------------------------------------------------- what breaks a file
class _RunsCode:
    """Unpickling this would create ``path``: a cache read must never run code from the file."""

    def __init__(self, path: Path):
        self.path = path

    def __reduce__(self):
        return (Path.touch, (self.path,))


def _tensor_dicts(state) -> list[dict]:
    """The dicts in ``state`` (nested) that hold tensors."""
    found = []
    if isinstance(state, dict):
        if any(isinstance(v, Tensor) for v in state.values()):
            found.append(state)
        for v in state.values():
            found += _tensor_dicts(v)
    elif isinstance(state, list | tuple):
        for v in state:
            found += _tensor_dicts(v)
    return found


def _truncate(path: Path, other: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _wrong_type(path: Path, other: Path) -> None:
    torch.save([1, 2, 3], path)


def _missing_key(path: Path, other: Path) -> None:
    state = torch.load(path, weights_only=True)
    tensors = _tensor_dicts(state)[0]
    del tensors[next(k for k, v in tensors.items() if isinstance(v, Tensor))]
    torch.save(state, path)


def _pickle_payload(path: Path, other: Path) -> None:
    torch.save({"payload": _RunsCode(path.parent / "code-ran")}, path)


def _symlink(path: Path, other: Path) -> None:
    target = path.parent.parent / "notes.txt"
    target.write_text("not a cache file\n")
    path.unlink()
    path.symlink_to(target)


def _nan(path: Path, other: Path) -> None:
    state = torch.load(path, weights_only=True)
    for tensors in _tensor_dicts(state):
        for value in tensors.values():
            if isinstance(value, Tensor) and value.is_floating_point() and value.numel():
                value[(0,) * value.dim()] = float("nan")
    torch.save(state, path)


def _other_entry(path: Path, other: Path) -> None:
    shutil.copyfile(other, path)


BREAKAGES = {"truncated": _truncate, "wrong type": _wrong_type, "missing key": _missing_key,
             "pickle payload": _pickle_payload, "symlink": _symlink, "NaN": _nan, "another entry": _other_entry}


def _other_file(root: Path, name: str) -> Path:
    case = CASES[name]
    return _files(root, name, case.other_split)[0] if case.other_split else _files(root, name)[1]


def _cache_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and r.name.startswith(CACHE_LOGGER)]


@pytest.mark.parametrize("breakage", BREAKAGES)
@pytest.mark.parametrize("name", CASES)
def test_a_broken_or_foreign_file_is_named_and_built_again(name, breakage, built, model, world_ckpt, tmp_path,
                                                          caplog):
    template, expected = built[name]
    root = tmp_path / "cache"
    shutil.copytree(template, root, symlinks=True)
    target = _files(root, name)[0]
    BREAKAGES[breakage](target, _other_file(root, name))
    with caplog.at_level(logging.WARNING, logger=CACHE_LOGGER):
        again = _load(name, model, world_ckpt, root)
    _assert_same(again, expected)
    messages = _cache_warnings(caplog)
    assert len(messages) == 1 and str(target) in messages[0] and "\n" not in messages[0], messages
    assert not (target.parent / "code-ran").exists()
    assert target.is_file() and not target.is_symlink()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=CACHE_LOGGER):
        _assert_same(_load(name, model, world_ckpt, root), expected)  # rebuilt for good: no warning the next time
    assert not _cache_warnings(caplog)


def test_an_agent_id_out_of_range_in_the_motion_cache_is_built_again(built, model, world_ckpt, tmp_path, caplog):
    template, expected = built["motion"]
    root = tmp_path / "cache"
    shutil.copytree(template, root)
    target = _files(root, "motion")[0]
    state = torch.load(target, weights_only=True)
    for tensors in _tensor_dicts(state):
        if "cells" in tensors:
            tensors["cells"][0, 0, 0] = 30000
    torch.save(state, target)
    with caplog.at_level(logging.WARNING, logger=CACHE_LOGGER):
        _assert_same(_load("motion", model, world_ckpt, root), expected)
    assert any(str(target) in m and "agent" in m for m in _cache_warnings(caplog))


@pytest.mark.parametrize("name", CASES)
def test_every_cache_keys_the_frames_per_scene(name, model, world_ckpt, tmp_path):
    """A 12-frame scene's cache is not read for 13 frames (one window of four strides each)."""
    _load(name, model, world_ckpt, tmp_path / "shared", frames=12, stride=4)
    reused = _load(name, model, world_ckpt, tmp_path / "shared", frames=13, stride=4)
    _assert_same(reused, _load(name, model, world_ckpt, tmp_path / "fresh", frames=13, stride=4))


# ---------------------------------------------------------------- box motion
class _Interrupted(Exception):
    """Stands for Ctrl-C (pytest would take a KeyboardInterrupt for its own)."""


def test_an_interrupted_box_cache_keeps_the_scenes_it_fitted(world_ckpt, tmp_path, monkeypatch):
    fitted = []
    real = box_cache.window_record

    def record(sample):
        if len(fitted) == 3:  # the second scene's second window
            raise _Interrupted
        fitted.append(1)
        return real(sample)

    cfg = _box_config(world_ckpt, tmp_path / "cache", frames=12)  # two windows a scene
    monkeypatch.setattr(box_cache, "window_record", record)
    with pytest.raises(_Interrupted):
        _box_samples(cfg)
    fitted.clear()
    resumed = _box_samples(cfg)
    assert len(fitted) == 2  # the second scene's two windows only
    monkeypatch.setattr(box_cache, "window_record", real)
    fresh = _box_config(world_ckpt, tmp_path / "fresh", frames=12)
    _assert_same(resumed, _box_samples(fresh))


def test_every_box_cache_write_has_its_own_temporary_file(world_ckpt, tmp_path, monkeypatch):
    """Two builders of the same cache never write through the same temporary file."""
    moves = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda src, dst: (moves.append((Path(src), Path(dst))), real(src, dst))[1])
    cfg = _box_config(world_ckpt, tmp_path / "cache", scenes=1)
    _box_samples(cfg)
    shutil.rmtree(tmp_path / "cache")
    _box_samples(cfg)
    assert len(moves) >= 2
    assert len({src for src, _ in moves}) == len(moves)
    assert all(src.parent == dst.parent for src, dst in moves)


def test_box_motion_refuses_more_scenes_than_its_split_holds(world_ckpt):
    for train, select in ((999_999, 40), (1_000_000, 1)):
        with pytest.raises(ConfigError, match=r"data\.train_scenes .*1,000,000") as info:
            BoxMotionTask(BoxMotionConfig(world_model=str(world_ckpt),
                                          data=BoxDataConfig(train_scenes=train, select_scenes=select)))
        assert "\n" not in str(info.value)
    BoxMotionTask(BoxMotionConfig(world_model=str(world_ckpt), data=BoxDataConfig(train_scenes=999_960)))
