"""Reports every benchmark group as a speed ratio: reference time / fused time (medians,
robust to a busy machine).

Each group holds one fused and one reference benchmark (parameter ``impl``); the ratios are
printed after the run and stored in the JSON (``--benchmark-json``) under ``"ratios"``.
"""

from __future__ import annotations

from collections import defaultdict


def _ratios(benchmarks) -> dict[str, dict[str, float]]:
    by_group: dict[str, dict[str, object]] = defaultdict(dict)
    for bench in benchmarks:
        impl = (bench.params or {}).get("impl")  # unparametrised benchmarks (data, training) have no pair
        if impl is not None:
            by_group[bench.group][impl] = bench
    out = {}
    for group, pair in sorted(by_group.items()):
        if len(pair) != 2:
            continue
        fused, ref = pair["fused"], pair["reference"]
        row = {
            "fused_s": fused.stats.median,
            "reference_s": ref.stats.median,
            "speedup": ref.stats.median / fused.stats.median,
        }
        if "peak_mb" in fused.extra_info and "peak_mb" in ref.extra_info:
            row["fused_peak_mb"] = fused.extra_info["peak_mb"]
            row["reference_peak_mb"] = ref.extra_info["peak_mb"]
            row["memory_ratio"] = ref.extra_info["peak_mb"] / max(fused.extra_info["peak_mb"], 1e-3)
        out[group] = row
    return out


def pytest_benchmark_update_json(config, benchmarks, output_json):
    output_json["ratios"] = _ratios(config._benchmarksession.benchmarks)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    session = getattr(config, "_benchmarksession", None)
    if session is None or not session.benchmarks:
        return
    ratios = _ratios(session.benchmarks)
    if not ratios:
        return
    tr = terminalreporter
    tr.section("t3fast: reference / fused")
    tr.write_line(f"{'group':<34}{'fused':>10}{'reference':>11}{'speedup':>9}{'memory':>22}")
    for group, r in ratios.items():
        mem = ""
        if "memory_ratio" in r:
            mem = f"{r['fused_peak_mb']:.0f} vs {r['reference_peak_mb']:.0f} MB"
            mem += f" ({r['memory_ratio']:.1f}x)"
        tr.write_line(
            f"{group:<34}{r['fused_s'] * 1e3:>8.1f}ms{r['reference_s'] * 1e3:>9.1f}ms"
            f"{r['speedup']:>8.2f}x{mem:>22}"
        )
