"""Config loading: YAML/JSON/dict sources, typed overrides, clear errors, round trip."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest
import yaml

from t3fast.io.config import ConfigError, config_to_dict, load_config, save_config
from t3fast.training.configs import TrainConfig


@dataclass
class ModelSection:
    hidden: list[int] = field(default_factory=lambda: [128, 128])
    grid: tuple[int, int, int] = (200, 200, 16)
    dropout: float | None = None
    name: str = "t3former"
    norm: Literal["group", "batch"] = "group"
    weights: Path | None = None


@dataclass
class Config:
    model: ModelSection = field(default_factory=ModelSection)
    train: TrainConfig = field(default_factory=TrainConfig)
    tags: dict[str, float] = field(default_factory=dict)


def test_defaults_without_source() -> None:
    assert load_config(Config) == Config()


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_file_sources(tmp_path: Path, suffix: str) -> None:
    data = {"model": {"hidden": [32, 16], "grid": [10, 10, 4]}, "train": {"lr": 0.002, "steps": 7}}
    path = tmp_path / f"cfg{suffix}"
    path.write_text(json.dumps(data) if suffix == ".json" else yaml.safe_dump(data))
    cfg = load_config(Config, path)
    assert cfg.model.hidden == [32, 16] and cfg.model.grid == (10, 10, 4)
    assert cfg.train.lr == 0.002 and cfg.train.steps == 7
    assert cfg.train.batch_size == TrainConfig().batch_size  # untouched fields keep their defaults


def test_overrides_are_coerced_to_field_types(tmp_path: Path) -> None:
    src = tmp_path / "cfg.yaml"
    src.write_text("train:\n  lr: 0.1\n  amp: true\n")
    cfg = load_config(
        Config,
        src,
        [
            "train.lr=3e-4",  # YAML 1.1 reads this as a string; the field type makes it a float
            "model.hidden=[64,64]",
            "train.amp=false",
            "train.steps=1e3",
            "train.grad_clip=null",
            "model.dropout=0.5",
            "model.name=on",  # a str field keeps the text (YAML would make it True)
            "model.norm=batch",
            "model.weights=ckpt/best.pt",
            "tags.a=1",
        ],
    )
    assert cfg.train.lr == pytest.approx(3e-4) and isinstance(cfg.train.lr, float)
    assert cfg.model.hidden == [64, 64]
    assert cfg.train.amp is False
    assert cfg.train.steps == 1000 and isinstance(cfg.train.steps, int)
    assert cfg.train.grad_clip is None
    assert cfg.model.dropout == 0.5
    assert cfg.model.name == "on"
    assert cfg.model.norm == "batch"
    assert cfg.model.weights == Path("ckpt/best.pt")
    assert cfg.tags == {"a": 1.0}


def test_dict_source_is_not_mutated() -> None:
    data = {"train": {"steps": 3}}
    load_config(Config, data, ["train.steps=5"])
    assert data == {"train": {"steps": 3}}


@pytest.mark.parametrize(
    ("source", "overrides", "match"),
    [
        ({"train": {"lrr": 1.0}}, [], r"unknown config key 'train\.lrr'.*valid keys: .*\blr\b"),
        (None, ["model.widht=3"], r"unknown config key 'model\.widht'.*hidden"),
        ({"optim": {}}, [], r"unknown config key 'optim'.*model, tags, train"),
        (None, ["train.steps=abc"], r"'train\.steps' must be int"),
        (None, ["train.amp=maybe"], r"'train\.amp' must be bool"),
        (None, ["model.norm=layer"], r"'model\.norm' must be one of"),
        (None, ["model.grid=[1,2]"], r"'model\.grid' must have 3 items"),
        (None, ["train.steps"], r"must look like 'section\.key=value'"),
        (None, ["train.lr=1", "train.lr.x=1"], r"'train\.lr' is not a section"),
        (None, ["train.lr.x=1"], r"'train\.lr' must be float"),
    ],
)
def test_bad_keys_and_values_raise(source: dict | None, overrides: list[str], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_config(Config, source, overrides)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_save_and_reload_round_trip(tmp_path: Path, suffix: str) -> None:
    cfg = load_config(Config, None, ["model.weights=a/b.pt", "train.grad_clip=null", "model.dropout=0.25"])
    path = tmp_path / f"saved{suffix}"
    save_config(cfg, path)
    assert load_config(Config, path) == cfg
    assert config_to_dict(cfg)["model"]["grid"] == [200, 200, 16]  # plain lists for YAML/JSON
