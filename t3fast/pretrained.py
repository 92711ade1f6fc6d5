"""Trained models for inference: ``t3fast.load_world_model("wm-small")``.

A name resolves to a checkpoint shipped in ``t3fast/checkpoints`` (like torchvision's and
timm's pretrained names); anything else is a path to a checkpoint that ``t3fast train-wm`` /
``t3fast train-ae`` wrote (``best.pt``, ``last.pt``) or ``t3fast export`` slimmed. Only the
model parts of a checkpoint's config are read, so checkpoints of every earlier version load
and inference never imports the training stack.

Every command that turns a checkpoint into a model does it here, and nothing is allocated
before the checkpoint is known to fit its config: the config's values are checked (a
:class:`~t3fast.errors.ConfigError` names the file, the key and the value), the model is
built on the ``meta`` device (shapes only, no memory) and its parameter count bounded by
:data:`MAX_PARAMETERS`, and every weight of the checkpoint is compared with the one the
config builds (a :class:`~t3fast.errors.CheckpointError` names the file, the weight and
both shapes) before the real model is built and loaded. :func:`export_weights` slims a
training checkpoint for shipping and replaces its output only with a file these loaders load.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import torch
from torch import nn

from t3fast.errors import CheckpointError, ConfigError, T3fastError, UsageError
from t3fast.io.checkpoint import AUTOENCODER, WORLD_MODEL, checkpoint_kind, read_checkpoint, save_checkpoint
from t3fast.io.config import load_config
from t3fast.models.autoencoder import TriplaneAutoencoder
from t3fast.models.config import AutoencoderConfig, WorldModelConfig
from t3fast.models.world_model import T3Former

SHIPPED_DIR = Path(__file__).parent / "checkpoints"

#: a config that builds more parameters than this is refused (the papers' model has ~1e7)
MAX_PARAMETERS = 2_000_000_000

M = TypeVar("M", bound=nn.Module)
C = TypeVar("C")
W = TypeVar("W", bound=T3Former)


def shipped_names() -> list[str]:
    """Names of the world models shipped with the package, e.g. ``["wm-small", ...]``."""
    return sorted(p.stem for p in SHIPPED_DIR.glob("*.pt"))


def resolve(name_or_path: str | Path) -> Path:
    """The checkpoint file of a shipped name or a path; a name that is neither is refused with
    the list of shipped names."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    shipped = SHIPPED_DIR / f"{path.name}.pt"
    if len(path.parts) == 1 and shipped.is_file():
        return shipped
    raise CheckpointError(f"{name_or_path}: neither a checkpoint file nor a shipped model "
                          f"({', '.join(shipped_names())})")


def load_world_model(name_or_path: str | Path, device: torch.device | str = "cpu", compile: bool = False) -> T3Former:
    """A trained :class:`T3Former` in eval mode on ``device``, from a shipped name
    (:func:`shipped_names`) or a stage-2 checkpoint path; with ``compile``, its forecast compiled
    whole (:meth:`T3Former.compile_forecast`: on CUDA one CUDA graph; the first forecast of each
    input shape compiles). Its sizes are in ``model.autoencoder_config`` and
    ``model.world_config``. A checkpoint that does not fit its config is refused
    (:class:`~t3fast.errors.CheckpointError`, :class:`~t3fast.errors.ConfigError`) before the
    model is allocated."""
    path = resolve(name_or_path)
    model = world_model_from_checkpoint(read_checkpoint(path, WORLD_MODEL), path).to(device).eval()
    return model.compile_forecast() if compile else model


def load_autoencoder(name_or_path: str | Path, device: torch.device | str = "cpu") -> TriplaneAutoencoder:
    """A trained :class:`TriplaneAutoencoder` in eval mode on ``device``, from a stage-1
    checkpoint, or the encoder and decoder of a world model (shipped name or stage-2 path);
    checked as :func:`load_world_model` checks."""
    path = resolve(name_or_path)
    return autoencoder_from_checkpoint(read_checkpoint(path, (AUTOENCODER, WORLD_MODEL)), path).to(device).eval()


def world_model_from_checkpoint(state: dict[str, Any], path: str | Path, model_class: type[W] = T3Former) -> W:
    """The :class:`T3Former` (on the CPU) of a stage-2 checkpoint ``state`` read from ``path``
    (:func:`~t3fast.io.checkpoint.read_checkpoint`), checked as the module says; a training task
    passes its ``model_class``, a :class:`T3Former` whose ``forward`` is the part it trains."""
    autoencoder = checkpoint_config(AutoencoderConfig, state, path, "autoencoder")
    world = checkpoint_config(WorldModelConfig, state, path, "model")
    return build_checked(lambda: model_class.from_config(autoencoder, world), state["model"], path,
                         lambda key: "task.autoencoder" if key.split(".", 1)[0] in ("encoder", "decoder")
                         else "task.model")


def autoencoder_from_checkpoint(state: dict[str, Any], path: str | Path) -> TriplaneAutoencoder:
    """The :class:`TriplaneAutoencoder` (on the CPU) of a stage-1 checkpoint, or the encoder and
    decoder of a stage-2 one, checked as the module says."""
    if checkpoint_kind(state) == WORLD_MODEL:
        key = "autoencoder"
        weights = {k: v for k, v in state["model"].items() if k.split(".", 1)[0] in ("encoder", "decoder")}
    else:
        key, weights = "model", state["model"]
    config = checkpoint_config(AutoencoderConfig, state, path, key)
    return build_checked(lambda: TriplaneAutoencoder(config), weights, path, lambda _: f"task.{key}")


def checkpoint_config(cls: type[C], state: dict[str, Any], path: str | Path, key: str | None = None) -> C:
    """``cls`` from the checkpoint's ``config.task`` (or its section ``key``); a missing or
    invalid section raises :class:`~t3fast.errors.ConfigError` naming the file and the key."""
    task = state["config"]["task"]
    where = "task" if key is None else f"task.{key}"
    source = task if key is None else task.get(key)
    if source is None:
        raise ConfigError(f"{path}: its config has no '{where}' (the sizes of the model to build)")
    if not isinstance(source, Mapping):
        raise ConfigError(f"{path}: config '{where}' must be a mapping of {cls.__name__} fields, "
                          f"got a {type(source).__name__}")
    try:
        return load_config(cls, source)
    except ValueError as exc:  # ConfigError, or a check of the config's own
        raise ConfigError(f"{path}: config '{where}': {exc}") from None


def build_checked(build: Callable[[], M], weights: Mapping[str, Any], path: str | Path,
                  section: Callable[[str], str]) -> M:
    """``build()`` loaded with ``weights``, once they are known to fit it.

    ``build`` runs first on the ``meta`` device; the model it describes must have at most
    :data:`MAX_PARAMETERS` numbers and exactly the weights' names and shapes (``section``
    names the config section a weight's sizes come from, for the message). Only then is the
    real model built (on the CPU) and the weights loaded into it.
    """
    try:
        with torch.device("meta"):
            skeleton = build()
    except (ValueError, TypeError, RuntimeError, AssertionError) as exc:  # a combination the config checks miss
        reason = (str(exc).strip().splitlines() or [""])[0]
        raise ConfigError(f"{path}: its config builds no model ({type(exc).__name__}: {reason})") from exc
    expected = skeleton.state_dict()
    count = sum(t.numel() for t in expected.values())
    if count > MAX_PARAMETERS:
        key, largest = max(expected.items(), key=lambda item: item[1].numel())
        raise ConfigError(f"{path}: its config builds a model of {count:,} parameters, more than the "
                          f"{MAX_PARAMETERS:,} loaded; the largest, {key!r} {list(largest.shape)}, is sized by "
                          f"config '{section(key)}'")
    check_weights(skeleton, expected, weights, path, section)
    model = build()
    model.load_state_dict(weights)
    return model


def check_weights(skeleton: nn.Module, expected: Mapping[str, torch.Tensor], weights: Mapping[str, Any],
                  path: str | Path, section: Callable[[str], str]) -> None:
    """Raises :class:`~t3fast.errors.CheckpointError` naming the first weight that is missing,
    unexpected, not a floating-point tensor where the model has one, or of another shape than
    the model built from the config (``expected``, the state_dict of ``skeleton``), and how
    many weights are wrong in all."""
    weights = dict(weights)
    for prefix, module in skeleton.named_modules():  # names of earlier versions, as loading renames them
        upgrade = getattr(module, "upgrade_state_dict", None)
        if upgrade is not None:
            upgrade(weights, f"{prefix}." if prefix else "")
    problems = []
    for key, want in expected.items():
        if key not in weights:
            problems.append(f"weight {key!r} is missing (the config '{section(key)}' builds it with shape "
                            f"{list(want.shape)})")
            continue
        got = weights[key]
        if not isinstance(got, torch.Tensor):
            problems.append(f"weight {key!r} is a {type(got).__name__}, not a tensor")
        elif want.is_floating_point() and not got.is_floating_point():
            problems.append(f"weight {key!r} has dtype {got.dtype}, not a floating-point one")
        elif got.shape != want.shape:
            problems.append(f"weight {key!r} has shape {list(got.shape)} but the config '{section(key)}' "
                            f"builds {list(want.shape)}")
    problems += [f"weight {key!r} is not part of the model its config '{section(str(key))}' builds"
                 for key in weights if key not in expected]
    if problems:
        more = f" (and {len(problems) - 1} more wrong weights)" if len(problems) > 1 else ""
        raise CheckpointError(f"{path}: {problems[0]}{more}")


def export_weights(src: str | Path, dst: str | Path, dtype: torch.dtype = torch.float16,
                   edit_config: Callable[[dict[str, Any], str | None], dict[str, Any]] | None = None) -> int:
    """Keep only what inference needs from a training checkpoint (model weights in ``dtype``,
    config, step), e.g. to ship it; returns the file size in bytes. Loading casts back to the
    model's dtype. ``src`` must be a stage-1 or stage-2 checkpoint (:func:`~t3fast.io.checkpoint.read_checkpoint`
    says what it is otherwise), read once. ``edit_config(config, kind)``: the config to store
    instead of the run's (``kind``: :func:`~t3fast.io.checkpoint.checkpoint_kind`), e.g. an inference setting.

    ``dst`` is replaced only by a file that loads: the written file is loaded as
    :func:`t3fast.load_world_model` (or :func:`t3fast.load_autoencoder`) loads it before it is
    renamed over ``dst``; a weight beyond the range of ``dtype`` is refused
    (:class:`~t3fast.errors.UsageError`) rather than stored as an infinity.
    """
    state = read_checkpoint(src, (AUTOENCODER, WORLD_MODEL))
    kind = checkpoint_kind(state)
    weights = {key: cast_weight(value, dtype, key, src) for key, value in state["model"].items()}
    config = state.get("config", {})
    if edit_config is not None:
        config = edit_config(config, kind)
    exported = {"model": weights, "config": config, "step": state.get("step")}
    save_checkpoint(exported, dst, check=lambda written: _check_loads(written, dst, kind))
    return Path(dst).stat().st_size


def cast_weight(value: torch.Tensor, dtype: torch.dtype, key: str, path: str | Path) -> torch.Tensor:
    """A floating-point ``value`` (finite, :func:`~t3fast.io.checkpoint.read_checkpoint`) in ``dtype``; one with values
    beyond the range of ``dtype`` (which the cast would make infinite) is refused with
    :class:`~t3fast.errors.UsageError` naming the weight and its largest magnitude."""
    if not value.is_floating_point():
        return value
    cast = value.to(dtype)
    if not bool(torch.isfinite(cast).all()):
        peak = float(value.abs().max())
        largest = torch.finfo(dtype).max
        wider = ": export it as float32 (--dtype float32)" if largest < torch.finfo(torch.float32).max else ""
        name = str(dtype).removeprefix("torch.")
        raise UsageError(f"{path}: weight {key!r} reaches {peak:g} in magnitude, beyond {name}'s {largest:g}{wider}")
    return cast


def _check_loads(written: Path, dst: str | Path, kind: str | None) -> None:
    """Load ``written`` (the export on its way to ``dst``) as users load it; a
    :class:`~t3fast.errors.T3fastError` it raises is raised again naming ``dst``."""
    load = load_world_model if kind == WORLD_MODEL else load_autoencoder
    try:
        load(written)
    except T3fastError as exc:
        reason = str(exc).removeprefix(f"{written}: ")
        raise type(exc)(f"{dst}: not written, the exported model would not load: {reason}") from None
