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
when installed), ``profile.json`` (with ``profile_steps``: where a step's time goes,
:mod:`t3fast.training.step_profile`). A new run needs an empty ``out_dir``; ``resume``
continues the run there and ``overwrite`` replaces it, keeping the old files until the new run
has set up, trained a step and written a checkpoint, and putting them back if it fails before
(:mod:`t3fast.training.run_dir`).

Finite numbers only: a step whose loss is not finite, or after which a weight is not, stops the
run with a :class:`~t3fast.errors.DivergenceError` naming the step and the loss term or weight,
before anything of that step is saved; no checkpoint is ever written with non-finite weights,
and none is resumed from (:mod:`t3fast.training.checkpoint_checks`).

Exact resume: a run resumed from ``last.pt`` takes the same steps as an uninterrupted one:
same weights, optimiser and scheduler state, batches and random streams. Randomness inside
DataLoader workers (``num_workers > 0``) is the exception after a mid-epoch resume: draw
augmentations in ``training_step`` or derive them from the sample index to keep it exact.
"""

from __future__ import annotations

import logging
import math
import time
from collections import defaultdict
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader

from t3fast.device import require_device
from t3fast.errors import CheckpointError, ConfigError, DivergenceError
from t3fast.io.checkpoint import first_nonfinite, save_checkpoint
from t3fast.io.config import config_to_dict
from t3fast.training.batch_sampler import ResumableBatchSampler
from t3fast.training.checkpoint_checks import load_weights, read_training_checkpoint
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
from t3fast.training.gathered import held_on_device
from t3fast.training.graphed_step import (
    WARMUP,
    GraphedStep,
    graph_optimizer,
    load_optimizer_state,
    portable_optimizer_state,
    portable_scheduler_state,
)
from t3fast.training.interrupt import StopRequest, ignore_sigint
from t3fast.training.metrics_log import MetricsLog
from t3fast.training.param_groups import param_groups
from t3fast.training.random_state import derive_seed, preserved_rng, rng_state, seed_everything, set_rng_state
from t3fast.training.run_dir import check_out_dir, drop_replaced, restore, set_aside
from t3fast.training.schedule import warmup_cosine
from t3fast.training.step_profile import SKIP, StepProfile
from t3fast.training.task import Task

log = logging.getLogger(__name__)


class Trainer:
    """Runs a :class:`Task` for ``cfg.steps`` optimiser steps; see the module docstring.

    Attributes after construction: ``model`` (possibly DDP-wrapped), ``module`` (plain),
    ``optimizer``, ``scheduler``, ``scaler``, ``device``, ``step`` (the resumed step when
    resuming), ``best_score``. After :meth:`fit`, ``interrupted`` tells whether Ctrl-C ended it.
    The caller ends a distributed run with :func:`t3fast.training.distributed.cleanup`.
    """

    def __init__(self, task: Task, cfg: TrainConfig) -> None:
        self.task, self.cfg = task, cfg
        self.device = init_distributed(require_device(cfg.device, "train.device"))
        self.rank, self.world = rank(), world_size()
        self.out_dir = Path(cfg.out_dir)
        check_out_dir(self.out_dir, cfg.resume, cfg.resume_from, cfg.overwrite)
        barrier()  # every rank has looked at out_dir before rank 0 writes to it
        if is_main():
            self.out_dir.mkdir(parents=True, exist_ok=True)

        seed_everything(cfg.seed)  # the same initial weights on every rank
        self.module = task.build_model().to(self.device)
        self.model: nn.Module = self.module
        # what the optimiser can change, checked for non-finite values after every step
        self._trainable = {name: p for name, p in self.module.named_parameters() if p.requires_grad}
        if self.world > 1:
            ids = [self.device.index] if self.device.type == "cuda" else None
            self.model = DistributedDataParallel(self.module, device_ids=ids)
        self.amp_dtype = _amp_dtype(cfg.amp, self.device)
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=self.amp_dtype == torch.float16)
        graphed = self._graphs_wanted()
        scales = task.lr_scales() if hasattr(task, "lr_scales") else None
        groups = param_groups(self.module, cfg.weight_decay, cfg.lr, scales)
        self.optimizer = (graph_optimizer(groups, cfg.lr, self.device) if graphed
                          else torch.optim.AdamW(groups, lr=cfg.lr))
        schedule = warmup_cosine(cfg.steps, min(cfg.warmup_steps, cfg.steps), cfg.lr, cfg.min_lr)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, schedule)
        self.scheduler.base_lrs = [float(lr) for lr in self.scheduler.base_lrs]  # rates written without a read
        #: the whole step replayed from a CUDA graph (train.cuda_graph), else None
        self.graphed = GraphedStep(self._whole_step, self.device) if graphed else None

        dataset = task.train_dataset()
        self.sampler = ResumableBatchSampler(len(dataset), cfg.batch_size, cfg.seed, self.rank, self.world)
        # a private generator: the loader's per-epoch worker seed must not draw from the global stream
        self._loader_gen = torch.Generator()
        on_device = held_on_device(dataset)
        if on_device and cfg.num_workers:
            log.info("train.num_workers=%d unused: the batches are gathered on %s, where workers cannot reach",
                     cfg.num_workers, self.device)
        self.loader = DataLoader(
            dataset,
            batch_sampler=self.sampler,
            collate_fn=task.collate,
            num_workers=0 if on_device else cfg.num_workers,
            pin_memory=self.device.type == "cuda" and not on_device,
            generator=self._loader_gen,
            worker_init_fn=ignore_sigint,
        )
        seed_everything(derive_seed(cfg.seed, self.rank))  # per-rank dropout/augmentation streams

        self.step = 0
        self.best_score = -math.inf
        self.interrupted = False
        self._stop = StopRequest(announce=is_main())
        self._last_eval_step = self._last_ckpt_step = -1
        self._reset_window()
        self._log = MetricsLog(self.out_dir, is_main(), cfg.tensorboard)
        # a graphed run profiles replayed steps: after each variant's eager warm-up and capture
        self._profile = StepProfile(self.out_dir / "profile.json", cfg.profile_steps if is_main() else 0, self.device,
                                    SKIP + (WARMUP + 1 if graphed else 0))
        self._maybe_resume()
        # overwrite: the old run moves aside only now that the new one is set up (a missing data
        # file, a bad init_from or a model too large leaves it untouched); see _save and fit
        self._replacing = bool(cfg.overwrite and is_main() and set_aside(self.out_dir))

    # ---- the loop -------------------------------------------------------------------------

    def fit(self) -> dict[str, float]:
        """Train from the current step to ``cfg.steps``; returns the final metrics.

        The result holds ``step``, ``best_score``, the last train log as ``train/<name>`` and
        the last evaluation as ``eval/<name>``. Ctrl-C stops after the current step, writes
        ``last.pt`` and returns (``self.interrupted`` is then True); a second Ctrl-C aborts.
        With ``overwrite``, an error before the first checkpoint after a training step puts the
        replaced run back. A loss or weight that is not finite raises :class:`DivergenceError`.
        """
        try:
            self._fit()
        except BaseException:
            if self._replacing:  # failed before it trained and saved: the replaced run comes back
                restore(self.out_dir)
                self._replacing = False
                log.warning("the run failed before its first checkpoint after a training step; restored the run "
                            "it replaced in %s", self.out_dir)
            raise
        return self._result()

    def _fit(self) -> None:
        self._log.open(self.cfg.steps, self.step)
        self._reset_window()
        batches = self._batches()
        try:
            with self._stop.installed():
                if self.cfg.eval_at_start and self.cfg.eval_every and self.step == 0:
                    self._evaluate()  # best.pt starts as the untrained model: training must beat it
                self.model.train()
                while self.step < self.cfg.steps:
                    self._profile.step_begin()
                    with self._profile.phase("data"):
                        batch = next(batches)
                    self._train_step(batch)
                    self._profile.step_done()
                    self._periodic()
                    if any_rank(self._stop.requested):  # all ranks stop at the same step
                        self.interrupted = True
                        self._save("last.pt")
                        break
                if not self.interrupted:
                    self._finish()
        finally:
            batches.close()
            self._profile.close()
            self._log.close()

    def _graphs_wanted(self) -> bool:
        """Whether the steps run from CUDA graphs (``train.cuda_graph``; on other devices, the
        same step without a graph): the task must name its steps' host-side choices."""
        if not self.cfg.cuda_graph:
            return False
        if not callable(getattr(self.task, "step_variant", None)):
            raise ConfigError(f"train.cuda_graph: {type(self.task).__name__} has no step_variant (the host-side "
                              "choices of a step), so its steps cannot be replayed from a graph; set "
                              "train.cuda_graph=false")
        if self.world > 1:
            log.warning("train.cuda_graph is off with %d processes (DistributedDataParallel): the steps run eagerly",
                        self.world)
            return False
        if self.scaler.is_enabled():
            log.warning("train.cuda_graph is off with float16 AMP (its loss scaler reads the device at every step): "
                        "the steps run eagerly")
            return False
        if self.device.type != "cuda":
            log.info("train.cuda_graph on %s: the graphed step runs without a graph", self.device)
        return True

    def _autocast(self) -> torch.autocast:
        return torch.autocast(self.device.type, dtype=self.amp_dtype, enabled=self.amp_dtype is not None)

    def _train_step(self, batch: Any) -> None:
        with self._profile.phase("data"):
            batch = _to_device(batch, self.device)
        if self.graphed is not None:
            with self._profile.phase("step"):
                terms = self.graphed(batch, self.task.step_variant())
            logs = self._read_and_check(terms)  # the graph changed no weight if the loss or a gradient was not finite
            self._advance(logs)
        else:
            self.optimizer.zero_grad(set_to_none=True)
            with self._profile.phase("forward"), self._autocast():
                loss, values = self.task.training_step(self.model, batch)
            with self._profile.phase("backward"):
                self.scaler.scale(loss).backward()
            with self._profile.phase("optimizer"):
                logs = self._update(loss, values)
        for k, v in logs.items():
            self._sums[k] += v
        self._count += 1
        self._samples += self.task.samples_in(batch)
        self._log.advance()

    def _update(self, loss: Tensor, values: dict[str, Tensor]) -> dict[str, float]:
        """Read the step's values and check them, clip, step the optimiser; the values read."""
        terms = {"loss": loss.detach(), **values}
        if self.cfg.grad_clip:  # None or 0: no clipping
            self.scaler.unscale_(self.optimizer)  # clip the true gradients, not the fp16-scaled ones
            terms["grad_norm"] = nn.utils.clip_grad_norm_(self.module.parameters(), self.cfg.grad_clip)
        # before the optimiser step: the weights stay those of the last good step
        logs = self._read_and_check(terms)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self._advance(logs)
        return logs

    def _whole_step(self, batch: Any) -> dict[str, Tensor]:
        """A step with nothing read on the host, what a CUDA graph holds: the loss, its backward,
        clipping and the fused optimiser step, which changes no weight when the loss or the
        gradient norm is not finite. Returns the values to log."""
        self.optimizer.zero_grad(set_to_none=True)  # the graph allocates the gradients it writes
        with self._autocast():
            loss, values = self.task.training_step(self.model, batch)
        loss.backward()
        params = list(self._trainable.values())
        if self.cfg.grad_clip:
            norm = nn.utils.clip_grad_norm_(params, self.cfg.grad_clip)
        else:
            norm = nn.utils.get_total_norm([p.grad for p in params if p.grad is not None])
        self.optimizer.found_inf = (~(loss.detach().isfinite() & norm.isfinite())).float()
        try:
            self.optimizer.step()
        finally:
            del self.optimizer.found_inf
        terms = {"loss": loss.detach(), **values}
        return terms | ({"grad_norm": norm} if self.cfg.grad_clip else {})

    def _read_and_check(self, terms: dict[str, Tensor | float]) -> dict[str, float]:
        """The step's values read at once; stop if the loss is not finite."""
        logs = read_values(terms)
        self._check_loss({k: v for k, v in logs.items() if k != "grad_norm"})
        logs["lr"] = float(self.optimizer.param_groups[0]["lr"])  # the rate this step uses
        return logs

    def _advance(self, logs: dict[str, float]) -> None:
        """After the optimiser step: the next rate, the step count, the weights checked."""
        self.scheduler.step()
        self.step += 1
        self._check_weights(logs["loss"])

    def _check_loss(self, logs: dict[str, float]) -> None:
        """Stop, on every rank at once, at the first step whose loss is not finite, naming the terms."""
        if not any_rank(not math.isfinite(logs["loss"])):
            return
        terms = ", ".join(f"{k}={v}" for k, v in logs.items() if not math.isfinite(v)) or "on another rank"
        raise DivergenceError(f"train step {self.step + 1}: the loss is not finite ({terms}); look for NaN or "
                              f"infinite values in the data, or lower train.lr ({self.cfg.lr:g}) or "
                              f"train.weight_decay ({self.cfg.weight_decay:g})")

    def _check_weights(self, loss: float) -> None:
        """Stop at the first step after which a weight is not finite (a finite loss can get there:
        a learning rate or weight decay far too large). The ranks hold the same weights."""
        name = first_nonfinite(self._trainable)
        if name is not None:
            raise DivergenceError(
                f"train step {self.step}: weight {name!r} is not finite after the optimiser step (the loss, "
                f"{loss:.4g}, was): lower train.lr ({self.cfg.lr:g}) or train.weight_decay ({self.cfg.weight_decay:g})"
            )

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
            self._loader_gen.manual_seed(derive_seed(self.cfg.seed, self.rank, epoch))
            yield from self.loader
            epoch, skip = epoch + 1, 0

    # ---- evaluation and logging -----------------------------------------------------------

    def _evaluate(self) -> None:
        self.model.eval()
        with preserved_rng(self.device), torch.no_grad():
            values = {k: float(v) for k, v in self.task.evaluate(self.module).items()}
        self.model.train()
        if "score" not in values:
            raise KeyError(f"Task.evaluate must return a 'score' (higher is better); got {sorted(values)}")
        self._last_eval_step = self.step
        self._log.emit("eval", self.step, values)
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
        self._log.emit("train", self.step, means)
        self._reset_window()

    def _reset_window(self) -> None:
        self._sums: dict[str, float] = defaultdict(float)
        self._count = 0
        self._samples = 0
        self._t0 = time.perf_counter()

    def _result(self) -> dict[str, float]:
        out = {"step": float(self.step), "best_score": self.best_score}
        for event in ("train", "eval"):
            out.update({f"{event}/{k}": v for k, v in self._log.last.get(event, {}).items()})
        return out

    # ---- checkpoints ----------------------------------------------------------------------

    def _save(self, name: str) -> None:
        """Write ``out_dir/name``; collective (every rank contributes its random state)."""
        bad = first_nonfinite(self.module.state_dict())  # also buffers, and the weights a task built
        if bad is not None:
            raise DivergenceError(f"weight {bad!r} is not finite at step {self.step}: {name} not written")
        rng = all_gather_object(rng_state(self.device))
        if is_main():
            save_checkpoint(self._state(rng), self.out_dir / name)
            # the run it replaces goes once the new one has trained (eval_at_start saves at step 0)
            if self._replacing and self.step > 0:
                drop_replaced(self.out_dir)
                self._replacing = False
        if name == "last.pt":
            self._last_ckpt_step = self.step

    def _state(self, rng: list[dict[str, Any]]) -> dict[str, Any]:
        config_dict = getattr(self.task, "config_dict", None)
        return {
            "model": self.module.state_dict(),
            "optimizer": portable_optimizer_state(self.optimizer),
            "scheduler": portable_scheduler_state(self.scheduler),
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
        state = read_training_checkpoint(path)
        load_weights(self.module, state["model"], path)
        try:  # before the scheduler: it holds the current lr
            load_optimizer_state(self.optimizer, state["optimizer"], self.device)
        except (ValueError, KeyError, TypeError) as exc:  # e.g. other parameter groups (lr_scales, frozen parts)
            raise CheckpointError(f"{path}: its optimizer state does not fit this run's ({exc}): it was written "
                                  "by a run with other training settings") from exc
        self.scheduler.load_state_dict(state["scheduler"])
        if self.scaler.is_enabled() and state["scaler"]:
            self.scaler.load_state_dict(state["scaler"])
        self.step = self._last_ckpt_step = int(state["step"])
        self.best_score = float(state["best_score"])
        rng = state["rng"]
        if len(rng) == self.world:
            set_rng_state(rng[self.rank], self.device)
        else:
            log.warning("checkpoint has random states of %d ranks, this run has %d: reseeding", len(rng), self.world)
            seed_everything(derive_seed(self.cfg.seed, self.rank, self.step))
        if is_main():
            self._log.drop_after(self.step)
            log.info("resumed from %s at step %d", path, self.step)

    def _resume_path(self) -> Path | None:
        if self.cfg.resume_from:
            path = Path(self.cfg.resume_from)
            if not path.is_file():
                raise FileNotFoundError(f"resume_from checkpoint {path} does not exist")
            return path
        # check_out_dir has made sure out_dir/last.pt exists when resuming
        return self.out_dir / "last.pt" if self.cfg.resume else None


def read_values(values: dict[str, Tensor | float]) -> dict[str, float]:
    """The values a step logs as floats: the tensors among them read from the device at once
    (one host synchronisation per step, after the backward, instead of one per value)."""
    tensors = {k: v for k, v in values.items() if isinstance(v, Tensor)}
    read = torch.stack([v.detach().double().reshape(()) for v in tensors.values()]).tolist() if tensors else []
    floats = dict(zip(tensors, read))
    return {k: floats[k] if k in floats else float(v) for k, v in values.items()}


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
