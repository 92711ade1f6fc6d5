"""A generic, resumable training loop: AdamW, warm-up + cosine, AMP, DDP, atomic checkpoints.

The trainer knows nothing about occupancy: a :class:`Task` supplies the model, the data,
the loss and the evaluation. Both training stages (triplane autoencoder, world model) run
through it::

    trainer = Trainer(MyTask(...), TrainConfig(steps=20_000, batch_size=4, out_dir="runs/stage1"))
    metrics = trainer.fit()

Multi-GPU: launch the same script with ``torchrun --nproc_per_node N``; the trainer joins the
process group, wraps the model in DistributedDataParallel, and shards every global batch.

Files in ``out_dir`` (written by rank 0): ``last.pt`` (every ``ckpt_every`` steps, at the end,
and on Ctrl-C), ``best.pt`` (whenever the evaluation score improves), ``metrics.jsonl`` (one
``{"event", "step", "time", "values"}`` object per log or evaluation), ``tb/`` (TensorBoard,
when installed). A new run needs an empty ``out_dir``; ``resume`` continues the run there and
``overwrite`` replaces it (:mod:`t3fast.training.run_dir`).

Exact resume: a run resumed from ``last.pt`` takes the same steps as an uninterrupted one:
same weights, optimiser and scheduler state, batches and random streams. Randomness inside
DataLoader workers (``num_workers > 0``) is the exception after a mid-epoch resume: draw
augmentations in ``training_step`` or derive them from the sample index to keep it exact.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import random
import signal
import threading
import time
from collections import defaultdict
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset, Sampler
from tqdm import tqdm

from t3fast.io.checkpoint import load_checkpoint, save_checkpoint
from t3fast.io.config import config_to_dict
from t3fast.training.configs import TrainConfig
from t3fast.training.distributed import (
    all_gather_object,
    all_reduce_mean,
    any_rank,
    barrier,
    init_distributed,
    is_main,
    rank,
    world_size,
)
from t3fast.training.run_dir import check_out_dir, clear_run
from t3fast.training.schedule import warmup_cosine

log = logging.getLogger(__name__)


@runtime_checkable
class Task(Protocol):
    """What a training job supplies to :class:`Trainer`.

    Methods:
        build_model: the trainable module. The trainer moves it to the device and, when
            distributed, wraps it in DistributedDataParallel.
        train_dataset: a map-style dataset (with ``len``).
        collate: turns a list of dataset items into a batch. The trainer moves the batch's
            tensors (in dicts, lists, tuples, or objects with a ``.to(device)``) to the device.
        training_step: ``(model, batch) -> (loss, values)``: the scalar loss to back-propagate
            and floats to log (the same keys on every rank). ``model`` may be the DDP wrapper:
            compute the loss through ``model(...)`` so gradients are synchronised. Runs under
            autocast when AMP is on.
        evaluate: ``model -> metrics``; must contain ``"score"`` (higher is better; decides
            ``best.pt``). Called on every rank with the plain module in eval mode under
            ``torch.no_grad()``; the task may all-reduce. Logged by rank 0. Random numbers drawn
            here do not disturb the training streams.
        samples_in: number of samples in a batch, for throughput.

    Optional: ``config_dict() -> dict`` of plain values (numbers, strings, lists, dicts), stored in
    checkpoints under ``state["config"]["task"]``; ``lr_scales() -> {submodule name: factor}``,
    learning-rate multipliers of parts of the model (e.g. a decoder being fine-tuned).
    """

    def build_model(self) -> nn.Module: ...

    def train_dataset(self) -> Dataset: ...

    def collate(self, batch_list: list[Any]) -> Any: ...

    def training_step(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]: ...

    def evaluate(self, model: nn.Module) -> dict[str, float]: ...

    def samples_in(self, batch: Any) -> int: ...


class ResumableBatchSampler(Sampler[list[int]]):
    """Deterministic, sharded, resumable batches of dataset indices.

    Epoch ``e`` draws one permutation from a generator seeded by ``(seed, e)``. Global batch
    ``b`` is ``perm[b*G:(b+1)*G]`` with ``G = batch_size * world_size``; rank ``r`` takes its
    ``r``-th slice of ``batch_size``. The incomplete tail is dropped so every rank takes the
    same number of steps. ``set_epoch(e, skip)`` starts the epoch at batch ``skip``.
    """

    def __init__(self, dataset_size: int, batch_size: int, seed: int, rank: int = 0, world_size: int = 1) -> None:
        self.dataset_size, self.batch_size, self.seed = dataset_size, batch_size, seed
        self.rank, self.world_size = rank, world_size
        self.batches_per_epoch = dataset_size // (batch_size * world_size)
        if self.batches_per_epoch == 0:
            raise ValueError(
                f"dataset of {dataset_size} samples is smaller than one global batch "
                f"({batch_size} per process x {world_size} processes)"
            )
        self.epoch, self.skip = 0, 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        """Choose the epoch to iterate and how many of its batches were already consumed."""
        self.epoch, self.skip = epoch, skip

    def __len__(self) -> int:
        return self.batches_per_epoch - self.skip

    def __iter__(self) -> Iterator[list[int]]:
        gen = torch.Generator().manual_seed(_derive_seed(self.seed, self.epoch))
        perm = torch.randperm(self.dataset_size, generator=gen).tolist()
        global_batch = self.batch_size * self.world_size
        for b in range(self.skip, self.batches_per_epoch):
            start = b * global_batch + self.rank * self.batch_size
            yield perm[start : start + self.batch_size]


class Trainer:
    """Runs a :class:`Task` for ``cfg.steps`` optimiser steps; see the module docstring.

    Attributes after construction: ``model`` (possibly DDP-wrapped), ``module`` (plain),
    ``optimizer``, ``scheduler``, ``scaler``, ``device``, ``step`` (the resumed step when
    resuming), ``best_score``. After :meth:`fit`, ``interrupted`` tells whether Ctrl-C ended it.
    The caller ends a distributed run with :func:`t3fast.training.distributed.cleanup`.
    """

    def __init__(self, task: Task, cfg: TrainConfig) -> None:
        self.task, self.cfg = task, cfg
        self.device = init_distributed(cfg.device)
        self.rank, self.world = rank(), world_size()
        self.out_dir = Path(cfg.out_dir)
        check_out_dir(self.out_dir, cfg.resume, cfg.resume_from, cfg.overwrite)
        barrier()  # every rank has looked at out_dir before rank 0 writes to it
        if is_main():
            if cfg.overwrite:
                clear_run(self.out_dir)
            self.out_dir.mkdir(parents=True, exist_ok=True)

        _seed_everything(cfg.seed)  # the same initial weights on every rank
        self.module = task.build_model().to(self.device)
        self.model: nn.Module = self.module
        if self.world > 1:
            ids = [self.device.index] if self.device.type == "cuda" else None
            self.model = DistributedDataParallel(self.module, device_ids=ids)
        scales = task.lr_scales() if hasattr(task, "lr_scales") else None
        self.optimizer = torch.optim.AdamW(param_groups(self.module, cfg.weight_decay, cfg.lr, scales), lr=cfg.lr)
        schedule = warmup_cosine(cfg.steps, min(cfg.warmup_steps, cfg.steps), cfg.lr, cfg.min_lr)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, schedule)
        self.amp_dtype = _amp_dtype(cfg.amp, self.device)
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=self.amp_dtype == torch.float16)

        dataset = task.train_dataset()
        self.sampler = ResumableBatchSampler(len(dataset), cfg.batch_size, cfg.seed, self.rank, self.world)
        # a private generator: the loader's per-epoch worker seed must not draw from the global stream
        self._loader_gen = torch.Generator()
        self.loader = DataLoader(
            dataset,
            batch_sampler=self.sampler,
            collate_fn=task.collate,
            num_workers=cfg.num_workers,
            pin_memory=self.device.type == "cuda",
            generator=self._loader_gen,
            worker_init_fn=_ignore_sigint,
        )
        _seed_everything(_derive_seed(cfg.seed, self.rank))  # per-rank dropout/augmentation streams

        self.step = 0
        self.best_score = -math.inf
        self.interrupted = False
        self._stop_requested = False
        self._last_eval_step = self._last_ckpt_step = -1
        self._last: dict[str, dict[str, float]] = {}
        self._reset_window()
        self._writer: Any = None
        self._bar: tqdm | None = None
        self._maybe_resume()

    # ---- the loop -------------------------------------------------------------------------

    def fit(self) -> dict[str, float]:
        """Train from the current step to ``cfg.steps``; returns the final metrics.

        The result holds ``step``, ``best_score``, the last train log as ``train/<name>`` and
        the last evaluation as ``eval/<name>``. Ctrl-C stops after the current step, writes
        ``last.pt`` and returns (``self.interrupted`` is then True); a second Ctrl-C aborts.
        """
        self._open_outputs()
        self._reset_window()
        batches = self._batches()
        try:
            with self._sigint_guard():
                if self.cfg.eval_at_start and self.cfg.eval_every and self.step == 0:
                    self._evaluate()  # best.pt starts as the untrained model: training must beat it
                self.model.train()
                while self.step < self.cfg.steps:
                    self._train_step(next(batches))
                    self._periodic()
                    if any_rank(self._stop_requested):  # all ranks stop at the same step
                        self.interrupted = True
                        self._save("last.pt")
                        break
                if not self.interrupted:
                    self._finish()
        finally:
            batches.close()
            self._close_outputs()
        return self._result()

    def _train_step(self, batch: Any) -> None:
        batch = _to_device(batch, self.device)
        self.optimizer.zero_grad(set_to_none=True)
        with torch.autocast(self.device.type, dtype=self.amp_dtype, enabled=self.amp_dtype is not None):
            loss, values = self.task.training_step(self.model, batch)
        self.scaler.scale(loss).backward()
        logs = {"loss": float(loss.detach()), **{k: float(v) for k, v in values.items()}}
        logs["lr"] = self.optimizer.param_groups[0]["lr"]  # the rate this step uses
        if self.cfg.grad_clip is not None:
            self.scaler.unscale_(self.optimizer)  # clip the true gradients, not the fp16-scaled ones
            logs["grad_norm"] = float(nn.utils.clip_grad_norm_(self.module.parameters(), self.cfg.grad_clip))
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        self.step += 1

        for k, v in logs.items():
            self._sums[k] += v
        self._count += 1
        self._samples += self.task.samples_in(batch)
        if self._bar is not None:
            self._bar.update(1)

    def _periodic(self) -> None:
        cfg, step = self.cfg, self.step
        if cfg.log_every and step % cfg.log_every == 0:
            self._log_train()
        if cfg.eval_every and step % cfg.eval_every == 0:
            self._evaluate()
        if cfg.ckpt_every and step % cfg.ckpt_every == 0:
            self._save("last.pt")

    def _finish(self) -> None:
        """End of training: flush the log window, evaluate and write last.pt unless just done."""
        if self._count:
            self._log_train()
        if self.cfg.eval_every and self._last_eval_step != self.step:
            self._evaluate()
        if self._last_ckpt_step != self.step:
            self._save("last.pt")

    def _batches(self) -> Iterator[Any]:
        """Batches from the current step on, epoch after epoch, exactly as an uninterrupted run sees them."""
        epoch, skip = divmod(self.step, self.sampler.batches_per_epoch)
        while True:
            self.sampler.set_epoch(epoch, skip)
            self._loader_gen.manual_seed(_derive_seed(self.cfg.seed, self.rank, epoch))
            yield from self.loader
            epoch, skip = epoch + 1, 0

    # ---- evaluation and logging -----------------------------------------------------------

    def _evaluate(self) -> None:
        self.model.eval()
        with _preserved_rng(self.device), torch.no_grad():
            values = {k: float(v) for k, v in self.task.evaluate(self.module).items()}
        self.model.train()
        if "score" not in values:
            raise KeyError(f"Task.evaluate must return a 'score' (higher is better); got {sorted(values)}")
        self._last_eval_step = self.step
        self._emit("eval", values)
        score = all_reduce_mean(values["score"])  # every rank must agree on saving (it is collective)
        if score > self.best_score:
            self.best_score = score
            self._save("best.pt")

    def _log_train(self) -> None:
        elapsed = time.perf_counter() - self._t0
        means = {k: v / self._count for k, v in self._sums.items()}
        means["samples"] = float(self._samples)
        means = all_reduce_mean(means)
        means["samples_per_s"] = means.pop("samples") * self.world / max(elapsed, 1e-9)
        self._emit("train", means)
        self._reset_window()

    def _reset_window(self) -> None:
        self._sums: dict[str, float] = defaultdict(float)
        self._count = 0
        self._samples = 0
        self._t0 = time.perf_counter()

    def _emit(self, event: str, values: dict[str, float]) -> None:
        """Record a log or evaluation event: metrics.jsonl, TensorBoard, progress bar (rank 0)."""
        self._last[event] = values
        if not is_main():
            return
        record = {"event": event, "step": self.step, "time": time.time(), "values": values}
        with open(self.out_dir / "metrics.jsonl", "a") as f:
            f.write(json.dumps(record) + "\n")
        if self._writer is not None:
            for k, v in values.items():
                self._writer.add_scalar(f"{event}/{k}", v, self.step)
        if self._bar is None:
            return
        if event == "train":
            loss, lr, rate = values["loss"], values["lr"], values["samples_per_s"]
            self._bar.set_postfix(loss=f"{loss:.4g}", lr=f"{lr:.3g}", samples_s=f"{rate:.1f}")
        else:
            self._bar.write(f"step {self.step} {event}: " + ", ".join(f"{k}={v:.4g}" for k, v in values.items()))

    def _open_outputs(self) -> None:
        if not is_main():
            return
        self._bar = tqdm(total=self.cfg.steps, initial=self.step, desc="train", dynamic_ncols=True)
        if self.cfg.tensorboard:
            self._writer = _tensorboard_writer(self.out_dir / "tb")

    def _close_outputs(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _result(self) -> dict[str, float]:
        out = {"step": float(self.step), "best_score": self.best_score}
        for event in ("train", "eval"):
            out.update({f"{event}/{k}": v for k, v in self._last.get(event, {}).items()})
        return out

    # ---- checkpoints ----------------------------------------------------------------------

    def _save(self, name: str) -> None:
        """Write ``out_dir/name``; collective (every rank contributes its random state)."""
        rng = all_gather_object(_rng_state(self.device))
        if is_main():
            save_checkpoint(self._state(rng), self.out_dir / name)
        if name == "last.pt":
            self._last_ckpt_step = self.step

    def _state(self, rng: list[dict[str, Any]]) -> dict[str, Any]:
        config_dict = getattr(self.task, "config_dict", None)
        return {
            "model": self.module.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "scaler": self.scaler.state_dict(),
            "step": self.step,
            "best_score": self.best_score,
            "rng": rng,  # one entry per rank
            "config": {
                "train": config_to_dict(self.cfg),
                "task": config_to_dict(config_dict()) if callable(config_dict) else None,
            },
        }

    def _maybe_resume(self) -> None:
        path = self._resume_path()
        if path is None:
            return
        state = load_checkpoint(path, map_location="cpu")
        self.module.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])  # before the scheduler: it holds the current lr
        self.scheduler.load_state_dict(state["scheduler"])
        if self.scaler.is_enabled() and state["scaler"]:
            self.scaler.load_state_dict(state["scaler"])
        self.step = self._last_ckpt_step = int(state["step"])
        self.best_score = float(state["best_score"])
        rng = state["rng"]
        if len(rng) == self.world:
            _set_rng_state(rng[self.rank], self.device)
        else:
            log.warning("checkpoint has random states of %d ranks, this run has %d: reseeding", len(rng), self.world)
            _seed_everything(_derive_seed(self.cfg.seed, self.rank, self.step))
        if is_main():
            _drop_metrics_after(self.out_dir / "metrics.jsonl", self.step)
            log.info("resumed from %s at step %d", path, self.step)

    def _resume_path(self) -> Path | None:
        if self.cfg.resume_from:
            path = Path(self.cfg.resume_from)
            if not path.is_file():
                raise FileNotFoundError(f"resume_from checkpoint {path} does not exist")
            return path
        # check_out_dir has made sure out_dir/last.pt exists when resuming
        return self.out_dir / "last.pt" if self.cfg.resume else None

    # ---- Ctrl-C ---------------------------------------------------------------------------

    @contextlib.contextmanager
    def _sigint_guard(self) -> Iterator[None]:
        """First Ctrl-C: finish the step, save, return. Second: KeyboardInterrupt at once."""
        if threading.current_thread() is not threading.main_thread():  # signal handlers live there only
            yield
            return

        def handler(signum: int, frame: Any) -> None:
            if self._stop_requested:
                raise KeyboardInterrupt
            self._stop_requested = True
            if is_main():
                tqdm.write("interrupted: saving last.pt after this step (Ctrl-C again to abort)")

        previous = signal.signal(signal.SIGINT, handler)
        try:
            yield
        finally:
            # None means a handler not installed from Python; the default is the closest we can restore
            signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)


def param_groups(
    model: nn.Module, weight_decay: float, lr: float | None = None, lr_scales: Mapping[str, float] | None = None
) -> list[dict[str, Any]]:
    """AdamW groups: decay on weight matrices/kernels; none on biases, norm weights (every 1-D
    parameter) and embedding tables. Frozen parameters are left out.

    ``lr_scales`` maps submodule names (``"decoder"``) to learning-rate multipliers; their
    parameters get groups of their own with ``lr = lr * scale``. Groups at the full rate come
    first (decay, then no decay)."""
    scales = dict(lr_scales or {})
    groups: dict[tuple[float, bool], list[nn.Parameter]] = {}
    seen: set[int] = set()
    for name, module in model.named_modules():
        scale = next((s for prefix, s in scales.items() if name == prefix or name.startswith(prefix + ".")), 1.0)
        for p in module.parameters(recurse=False):
            if not p.requires_grad or id(p) in seen:  # shared parameters appear once
                continue
            seen.add(id(p))
            exempt = p.ndim < 2 or isinstance(module, nn.Embedding | nn.EmbeddingBag)
            groups.setdefault((scale, exempt), []).append(p)
    ordered = sorted(groups, key=lambda key: (key[0] != 1.0, -key[0], key[1]))
    return [
        {"params": groups[key], "weight_decay": 0.0 if key[1] else weight_decay}
        | ({} if lr is None else {"lr": lr * key[0]})
        for key in ordered
    ]


def _amp_dtype(enabled: bool, device: torch.device) -> torch.dtype | None:
    if not enabled or device.type != "cuda":
        return None
    return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16


def _to_device(obj: Any, device: torch.device) -> Any:
    """Move the tensors of a batch (nested dicts/lists/tuples, or objects with ``.to``) to ``device``."""
    if isinstance(obj, torch.Tensor):
        return obj.to(device, non_blocking=True)
    if isinstance(obj, Mapping):
        return {k: _to_device(v, device) for k, v in obj.items()}
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):  # namedtuple
        return type(obj)(*(_to_device(v, device) for v in obj))
    if isinstance(obj, list | tuple):
        return type(obj)(_to_device(v, device) for v in obj)
    if callable(getattr(obj, "to", None)):
        return obj.to(device)
    return obj


def _derive_seed(*parts: int) -> int:
    """A 63-bit seed from several integers, with no collisions between e.g. (1, 0) and (0, 1)."""
    digest = hashlib.blake2b(repr(parts).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)  # also seeds every CUDA device


def _rng_state(device: torch.device) -> dict[str, Any]:
    """The random streams of this process, as plain values (loadable with ``weights_only=True``)."""
    kind, key, pos, has_gauss, gauss = np.random.get_state()
    state: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": [kind, torch.from_numpy(key.astype(np.int64)), int(pos), int(has_gauss), float(gauss)],
        "torch": torch.get_rng_state(),
    }
    if device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def _set_rng_state(state: dict[str, Any], device: torch.device) -> None:
    random.setstate(state["python"])
    kind, key, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((kind, key.numpy().astype(np.uint32), pos, has_gauss, gauss))
    torch.set_rng_state(state["torch"])
    if device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(state["cuda"], device)


@contextlib.contextmanager
def _preserved_rng(device: torch.device) -> Iterator[None]:
    """Run a block without moving the random streams (evaluation must not change training)."""
    state = _rng_state(device)
    try:
        yield
    finally:
        _set_rng_state(state, device)


def _drop_metrics_after(path: Path, step: int) -> None:
    """On resume, forget the events the interrupted run logged after its checkpoint."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines(keepends=True)
    kept = [line for line in lines if line.strip() and json.loads(line)["step"] <= step]
    if len(kept) != len(lines):
        path.write_text("".join(kept))


def _ignore_sigint(worker_id: int) -> None:
    """DataLoader workers leave Ctrl-C to the main process, which stops cleanly and shuts them down."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _tensorboard_writer(log_dir: Path) -> Any:
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # tensorboard is optional
        return None
    return SummaryWriter(str(log_dir))
