"""Peak extra memory of one op call.

CPU: measured in a fresh subprocess. The resident-set high-water mark (VmHWM) is reset after
the inputs exist, the op runs once, and the growth of the high-water mark over the resident
set before the call is the op's peak working memory (outputs included).

CUDA (``T3FAST_BENCH_DEVICE=cuda``): the same growth, read from the caching allocator
(``torch.cuda.max_memory_allocated`` over ``memory_allocated`` before the call), in process.
"""

from __future__ import annotations

import json
import subprocess
import sys

_SCRIPT = r"""
import json, sys
import torch
sys.path.insert(0, {bench_dir!r})
from workloads import make_decode_inputs, run_decode

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) / 1024
    raise KeyError(key)

args = make_decode_inputs(**{cfg})
with torch.no_grad():
    run_decode({impl!r}, args, {query!r})  # warm-up: allocator pools, thread pools
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = status("VmRSS")
    out = run_decode({impl!r}, args, {query!r})
    peak = status("VmHWM")
print(json.dumps({{"peak_mb": peak - before}}))
"""


def peak_memory_mb(impl: str, cfg: dict, query: str) -> float | None:
    """Peak working memory of ``run_decode(impl, make_decode_inputs(**cfg), query)`` in MB;
    None in quick mode on the CPU (a subprocess per benchmark is too slow for a dry run)."""
    import os

    from workloads import DEVICE, QUICK

    if DEVICE == "cuda":
        return _cuda_peak_memory_mb(impl, cfg, query)
    if QUICK:
        return None
    script = _SCRIPT.format(
        bench_dir=os.path.dirname(os.path.abspath(__file__)), cfg=cfg, impl=impl, query=query
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["peak_mb"]


def _cuda_peak_memory_mb(impl: str, cfg: dict, query: str) -> float:
    import torch
    from workloads import make_decode_inputs, run_decode

    args = make_decode_inputs(**cfg, device="cuda")
    with torch.no_grad():
        run_decode(impl, args, query)  # warm-up: allocator pools, kernels loaded
        torch.cuda.synchronize()
        before = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
        out = run_decode(impl, args, query)
        torch.cuda.synchronize()
        peak = torch.cuda.max_memory_allocated()
    del out
    return (peak - before) / 2**20
