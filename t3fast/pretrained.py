"""Trained models for inference: ``t3fast.load_world_model("wm-small")``.

A name resolves to a checkpoint shipped in ``t3fast/checkpoints`` (like torchvision's and
timm's pretrained names); anything else is a path to a checkpoint that ``t3fast train-wm`` /
``t3fast train-ae`` wrote (``best.pt``, ``last.pt``) or ``t3fast export`` slimmed. Only the
model parts of a checkpoint's config are read, so checkpoints of every earlier version load
and inference never imports the training stack.
"""

from __future__ import annotations

from pathlib import Path

import torch

from t3fast.errors import CheckpointError
from t3fast.io.checkpoint import AUTOENCODER, WORLD_MODEL, checkpoint_kind, read_checkpoint
from t3fast.io.config import load_config
from t3fast.models.autoencoder import TriplaneAutoencoder
from t3fast.models.config import AutoencoderConfig, WorldModelConfig
from t3fast.models.world_model import T3Former

SHIPPED_DIR = Path(__file__).parent / "checkpoints"


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


def load_world_model(name_or_path: str | Path, device: torch.device | str = "cpu") -> T3Former:
    """A trained :class:`T3Former` in eval mode on ``device``, from a shipped name
    (:func:`shipped_names`) or a stage-2 checkpoint path. Its sizes are in
    ``model.autoencoder_config`` and ``model.world_config``."""
    state = read_checkpoint(resolve(name_or_path), WORLD_MODEL)
    task = state["config"]["task"]
    model = T3Former.from_config(load_config(AutoencoderConfig, task["autoencoder"]),
                                 load_config(WorldModelConfig, task["model"]))
    model.load_state_dict(state["model"])
    return model.to(device).eval()


def load_autoencoder(name_or_path: str | Path, device: torch.device | str = "cpu") -> TriplaneAutoencoder:
    """A trained :class:`TriplaneAutoencoder` in eval mode on ``device``, from a stage-1
    checkpoint, or the encoder and decoder of a world model (shipped name or stage-2 path)."""
    path = resolve(name_or_path)
    state = read_checkpoint(path, (AUTOENCODER, WORLD_MODEL))
    task = state["config"]["task"]
    if checkpoint_kind(state) == WORLD_MODEL:
        config = load_config(AutoencoderConfig, task["autoencoder"])
        weights = {k: v for k, v in state["model"].items() if k.split(".", 1)[0] in ("encoder", "decoder")}
    else:
        config, weights = load_config(AutoencoderConfig, task["model"]), state["model"]
    model = TriplaneAutoencoder(config)
    model.load_state_dict(weights)
    return model.to(device).eval()

