"""Peak extra memory of one op call, measured in a fresh subprocess.

The resident-set high-water mark (VmHWM) is reset after the inputs exist, the op runs
once, and the growth of the high-water mark over the resident set before the call is the
op's peak working memory (outputs included).
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


def peak_memory_mb(impl: str, cfg: dict, query: str) -> float:
    import os

    script = _SCRIPT.format(
        bench_dir=os.path.dirname(os.path.abspath(__file__)), cfg=cfg, impl=impl, query=query
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["peak_mb"]
