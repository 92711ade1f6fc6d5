"""What a run reports: ``metrics.jsonl``, TensorBoard (when installed) and the progress bar."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm


class MetricsLog:
    """Events ``{"event", "step", "time", "values"}`` of one run. Only the writing process
    (``writes``: rank 0) touches files and the terminal; every process keeps the last values."""

    def __init__(self, out_dir: Path, writes: bool, tensorboard: bool) -> None:
        self.path = out_dir / "metrics.jsonl"
        self.writes, self.tensorboard = writes, tensorboard
        self.last: dict[str, dict[str, float]] = {}
        self._bar: tqdm | None = None
        self._writer: Any = None

    def open(self, total: int, initial: int) -> None:
        if not self.writes:
            return
        self._bar = tqdm(total=total, initial=initial, desc="train", dynamic_ncols=True)
        if self.tensorboard:
            self._writer = _tensorboard_writer(self.path.parent / "tb")

    def advance(self) -> None:
        """One optimiser step done."""
        if self._bar is not None:
            self._bar.update(1)

    def emit(self, event: str, step: int, values: dict[str, float]) -> None:
        """Record a log (``"train"``) or evaluation (``"eval"``) event."""
        self.last[event] = values
        if not self.writes:
            return
        record = {"event": event, "step": step, "time": time.time(), "values": values}
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
        if self._writer is not None:
            for k, v in values.items():
                self._writer.add_scalar(f"{event}/{k}", v, step)
        if self._bar is None:
            return
        if event == "train":
            loss, lr, rate = values["loss"], values["lr"], values["samples_per_s"]
            self._bar.set_postfix(loss=f"{loss:.4g}", lr=f"{lr:.3g}", samples_s=f"{rate:.1f}")
        else:
            self._bar.write(f"step {step} {event}: " + ", ".join(f"{k}={v:.4g}" for k, v in values.items()))

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def drop_after(self, step: int) -> None:
        """On resume, forget the events the interrupted run logged after its checkpoint."""
        if not (self.writes and self.path.is_file()):
            return
        lines = self.path.read_text().splitlines(keepends=True)
        kept = [line for line in lines if line.strip() and json.loads(line)["step"] <= step]
        if len(kept) != len(lines):
            self.path.write_text("".join(kept))


def _tensorboard_writer(log_dir: Path) -> Any:
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # tensorboard is optional
        return None
    return SummaryWriter(str(log_dir))
