"""Reading info pickles at the limits: a frame of the most boxes allowed, and a small file
claiming a huge array. Run with ``pytest benchmarks/test_bench_info.py --benchmark-only``.
"""

from __future__ import annotations

import pickle

import pytest

from t3fast.data.occ3d import MAX_BOXES, read_infos
from t3fast.errors import DataFormatError


def _info_file(tmp_path, **fields) -> str:
    frame = {"token": "t0", "ego2global_translation": [0.0, 0.0, 0.0], "ego2global_rotation": [1.0, 0.0, 0.0, 0.0]}
    path = tmp_path / "infos.pkl"
    path.write_bytes(pickle.dumps({"infos": {"scene-0001": [{**frame, **fields}]}}))
    return path


def _frame_of_most_boxes(last_token: str | None = None) -> dict:
    tokens = [f"instance-{i}" for i in range(MAX_BOXES)]
    if last_token is not None:
        tokens[-1] = last_token
    return {
        "gt_boxes": [[float(i), 0.0, 0.0, 4.0, 2.0, 1.5, 0.0] for i in range(MAX_BOXES)],
        "gt_names": ["car"] * MAX_BOXES,
        "instance_tokens": tokens,
    }


def test_read_frame_of_most_boxes(benchmark, tmp_path):
    benchmark.group = f"info pickle: one frame of {MAX_BOXES:,} boxes as lists"
    path = _info_file(tmp_path, **_frame_of_most_boxes())
    benchmark.pedantic(read_infos, (path,), rounds=5)


def test_refuse_repeated_token_at_the_end(benchmark, tmp_path):
    """The repeated token is the last but one: a scan per token would be quadratic."""
    benchmark.group = f"info pickle: one frame of {MAX_BOXES:,} boxes, a token repeated at the end"
    path = _info_file(tmp_path, **_frame_of_most_boxes(last_token=f"instance-{MAX_BOXES - 2}"))

    def refuse():
        with pytest.raises(DataFormatError, match="twice"):
            read_infos(path)

    benchmark.pedantic(refuse, rounds=5)


def test_refuse_shared_nested_claim(benchmark, tmp_path):
    """Nested lists repeating one inner list: 1000 x 1000 x 1000 x 7 claimed by a file of a few KB."""
    benchmark.group = "info pickle: refuse 'gt_boxes' claiming 1000 x 1000 x 1000 x 7"
    row = [0.0] * 7
    path = _info_file(tmp_path, gt_boxes=[[[row] * 1000] * 1000] * 1000)

    def refuse():
        with pytest.raises(DataFormatError, match="holds more than"):
            read_infos(path)

    benchmark.pedantic(refuse, rounds=5)
