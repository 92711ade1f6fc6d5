"""What the learning-curve tools share: reading a run's ``metrics.jsonl``, labelling a panel,
and the command line ``TOOL METRICS.jsonl OUT.png``."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")


def read_events(metrics: Path) -> tuple[list[dict], list[dict]]:
    """The train and the eval records of a run's ``metrics.jsonl``."""
    records = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    return [r for r in records if r["event"] == "train"], [r for r in records if r["event"] == "eval"]


def label_panel(panel, ylabel: str, title: str) -> None:
    """Steps along x, ``ylabel`` along y, a legend and ``title``."""
    panel.set_xlabel("step")
    panel.set_ylabel(ylabel)
    panel.legend(fontsize=8)
    panel.set_title(title)


def run(main: Callable[[Path, Path], None], doc: str) -> None:
    """``main(METRICS.jsonl, OUT.png)`` from the command line; the first line of ``doc`` on misuse."""
    if len(sys.argv) != 3:
        raise SystemExit(doc.splitlines()[0])
    main(Path(sys.argv[1]), Path(sys.argv[2]))
