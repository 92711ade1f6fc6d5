"""Synthetic data generation speed (the target is a 40-frame scene in under 2 s on one core).

Run on one core with ``taskset -c 0 pytest benchmarks/test_bench_data.py --benchmark-only``.
"""

from __future__ import annotations

from t3fast.data.synthetic.dataset import scene_seed
from t3fast.data.synthetic.scene import generate_scene


def test_generate_40_frame_scene(benchmark):
    benchmark.group = "synthetic scene (40 frames)"
    generate_scene(scene_seed("test", 0), 12)  # one-off tables
    seeds = iter(range(1, 100))
    benchmark.pedantic(lambda: generate_scene(scene_seed("test", next(seeds)), 40), rounds=5)
