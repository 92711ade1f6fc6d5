"""Markdown tables from the folder a GPU check wrote: ``python -m benchmarks.gpu.report OUTDIR``.

Prints the stages' status, the CUDA test counts, the op benchmarks (fused against reference,
achieved TFLOP/s and GB/s, fraction of the roofline), the forecasting step (FPS, memory) and
the training bursts (samples/s). Paste the output into the README, or redirect it to
``benchmarks/results/gpu/report.md``.

Roofline: the compute roof is the GPU's dense peak in the precision the fused run computes in
(``extra_info["precision"]``: fp32 on CUDA cores, the default; tf32 or bf16 on tensor cores);
the memory roof is its HBM bandwidth. For a workload of F FLOPs and B compulsory bytes taking t
seconds the attainable rate is ``min(P, (F / B) * BW)`` and the table gives
``(F / t) / attainable``. The peaks are looked up
from the GPU's name (table ``PEAKS``) or given with ``--peak-tflops`` / ``--peak-gbps``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

try:
    from .run import junit_counts
except ImportError:  # run as a script: benchmarks/gpu/report.py
    from run import junit_counts

# name fragment -> (dense fp32 TFLOP/s without tensor cores, dense TF32 and bf16 tensor TFLOP/s,
# HBM GB/s); vendor datasheet figures (dense: half the sparse ones), first match wins (most
# specific first)
PEAKS = {
    "H200": (67.0, 494.5, 989.0, 4800.0),
    "H100 PCIe": (51.0, 378.0, 756.0, 2000.0),
    "H100 NVL": (60.0, 417.5, 835.0, 3900.0),
    "H100": (67.0, 494.5, 989.0, 3350.0),  # SXM (HBM3)
    "A100-SXM4-80GB": (19.5, 156.0, 312.0, 2039.0),
    "A100 80GB PCIe": (19.5, 156.0, 312.0, 1935.0),
    "A100": (19.5, 156.0, 312.0, 1555.0),  # 40 GB
    "L40S": (91.6, 183.0, 362.0, 864.0),
    "RTX 4090": (82.6, 82.6, 165.0, 1008.0),
}
# precision of a benchmark -> its compute roof's index in a PEAKS entry
ROOF_INDEX = {"fp32": 0, "tf32": 1, "bf16": 2, "fp16": 2}
HBM = 3  # index of the memory roof


def peaks_for(gpu: str | None) -> tuple[str, tuple[float, float, float]] | None:
    if not gpu:
        return None
    for fragment, peaks in PEAKS.items():
        if fragment.lower() in gpu.lower():
            return fragment, peaks
    return None


def _read_json(path: Path):
    return json.loads(path.read_text()) if path.is_file() else None


def _read_jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _fmt(value, spec: str = ".2f", missing: str = "–") -> str:
    return missing if value is None else format(value, spec)


def _table(header: list[str], rows: list[list[str]], right: set[int] = frozenset()) -> list[str]:
    lines = ["| " + " | ".join(header) + " |",
             "|" + "|".join("---:" if i in right else "---" for i in range(len(header))) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


def header_section(out: Path) -> list[str]:
    env = _read_json(out / "env" / "env.json") or {}
    build = _read_json(out / "build" / "build_info.json") or {}
    summary = _read_json(out / "summary.json") or {}
    gpus = ", ".join(g["name"] for g in env.get("gpus", [])) or "no GPU"
    lines = [f"**{gpus}**; torch {env.get('torch', '?')}, CUDA {env.get('torch_cuda') or '–'}, "
             f"NCCL {env.get('nccl') or '–'}, Python {env.get('python', '?')}; "
             f"kernels built with CUDA: {build.get('cuda', '?')}; commit {summary.get('commit') or '?'}, "
             f"run {summary.get('started', '?')} ({'dry run, ' if summary.get('quick') else ''}"
             f"device {summary.get('device', '?')})."]
    return lines


def stages_section(out: Path) -> list[str]:
    summary = _read_json(out / "summary.json")
    if summary is None:
        return ["No summary.json: the run did not start."]
    rows = [[s["name"], s["status"], _fmt(s.get("seconds"), ".0f"), s.get("detail", "")] for s in summary["stages"]]
    return _table(["stage", "status", "time (s)", "detail"], rows, {2})


def ops_section(out: Path, peaks: tuple[float, float, float, float] | None) -> list[str]:
    data = _read_json(out / "ops" / "benchmarks.json")
    if data is None:
        return ["No op benchmarks (ops/benchmarks.json missing)."]
    by_group: dict[str, dict[str, dict]] = {}
    for bench in data["benchmarks"]:
        by_group.setdefault(bench["group"], {})[bench["params"]["impl"]] = bench
    rows = []
    for group, pair in by_group.items():
        fused, ref = pair.get("fused"), pair.get("reference")
        t_f = fused["stats"]["median"] if fused else None
        t_r = ref["stats"]["median"] if ref else None
        info = (fused or ref)["extra_info"]
        flops, nbytes = info.get("flops"), info.get("bytes")
        precision = info.get("precision", "fp32")
        tflops = flops / t_f / 1e12 if flops and t_f else None
        gbps = nbytes / t_f / 1e9 if nbytes and t_f else None
        roof, bound = None, "–"
        if peaks and flops and nbytes and t_f:
            peak_flops, peak_bw = peaks[ROOF_INDEX[precision]] * 1e12, peaks[HBM] * 1e9
            attainable = min(peak_flops, flops / nbytes * peak_bw)
            bound = "compute" if attainable == peak_flops else "memory"
            roof = 100 * (flops / t_f) / attainable
        mem = "–"
        if fused and ref and "peak_mb" in fused["extra_info"] and "peak_mb" in ref["extra_info"]:
            mem = f"{fused['extra_info']['peak_mb']:.0f} / {ref['extra_info']['peak_mb']:.0f}"
        rows.append([
            group, precision, _fmt(t_f and t_f * 1e3, ".3f"), _fmt(t_r and t_r * 1e3, ".3f"),
            _fmt(t_r / t_f if t_f and t_r else None, ".1f") + ("x" if t_f and t_r else ""),
            _fmt(flops and flops / 1e9, ".2f"), _fmt(nbytes and nbytes / 1e6, ".1f"),
            _fmt(tflops, ".2f"), _fmt(gbps, ".0f"), _fmt(flops and nbytes and flops / nbytes, ".1f"),
            bound, _fmt(roof, ".1f"), mem,
        ])
    header = ["workload", "precision", "fused (ms)", "reference (ms)", "speedup", "GFLOP", "MB moved", "fused TFLOP/s",
              "fused GB/s", "FLOP/byte", "bound", "% of roofline", "peak MB fused / ref"]
    lines = _table(header, rows, set(range(2, 13)) - {10})
    if peaks:
        lines += ["", f"Roofline: {peaks[0]:g} TFLOP/s dense fp32 (CUDA cores), {peaks[1]:g} TFLOP/s dense TF32 and "
                      f"{peaks[2]:g} TFLOP/s dense bf16 (tensor cores), {peaks[HBM] / 1000:g} TB/s HBM; each row "
                      "against the compute roof of its precision (fp32: float32 inputs without TF32; tf32: "
                      "allow_tf32 on; bf16: float32 inputs under bfloat16 autocast). Bytes are compulsory traffic "
                      "(inputs read once, outputs written once); medians of pytest-benchmark rounds."]
    else:
        lines += ["", "No roofline: unknown device peaks (give --peak-tflops and --peak-gbps)."]
    return lines


def forecast_section(out: Path) -> list[str]:
    rows = _read_jsonl(out / "forecast" / "results.jsonl")
    if not rows:
        return ["No forecasting results (forecast/results.jsonl missing)."]
    body = []
    for r in rows:
        if "error" in r:
            body.append([r["size"], r["mode"], str(r.get("batch", 1)), "error", "", "", "", "", r["error"][:80]])
            continue
        body.append([r["size"], r["mode"], str(r.get("batch", 1)), _fmt(r["median_ms"], ".2f"),
                     _fmt(r["p90_ms"], ".2f"), _fmt(r["fps"], ".1f"),
                     _fmt(r.get("peak_allocated_mb"), ".0f"), _fmt(r.get("peak_reserved_mb"), ".0f"),
                     f"{r['params_m']:.2f} M params, set-up {r['setup_s']:.1f} s, {r['iters']} steps timed"
                     + (f", {r['kernels']} kernels, GPU busy {r['gpu_busy_ms']:.2f} ms" if "kernels" in r else "")
                     + (f", {r['host_syncs']} host syncs" if "host_syncs" in r else "")])
    header = ["size", "mode", "batch", "median (ms)", "p90 (ms)", "FPS", "peak allocated (MB)", "peak reserved (MB)",
              "notes"]
    return _table(header, body, {2, 3, 4, 5, 6, 7}) + [
        "", "The whole `model.forecast(past labels, past poses)` of a validation window: encoding the 5 past frames, "
            "the agents, the forecaster, the planner, the 6 frames rendered to labels; FPS = windows per second. "
            "Kernels and GPU busy time: one more call under torch.profiler (the kernels that took it: `profile/`)."]


def training_section(out: Path) -> list[str]:
    body = []
    shipped = sorted(str(p.parent.relative_to(out)) for p in out.glob("train_shipped/*/result.json"))
    for stage in ("train_ae", "train_wm", "train_wm/eager", *shipped):
        r = _read_json(out / stage / "result.json")
        if r is None:  # killed before rank 0 wrote it: what the trainer had logged
            windows = [e["values"]["samples_per_s"] for e in _read_jsonl(out / stage / "run" / "metrics.jsonl")
                       if e.get("event") == "train"]
            if windows or stage != "train_wm/eager":
                rate = statistics.median(windows[1:] or windows) if windows else None
                body.append([f"{stage} (no result.json)", "", "", "", "", f"{len(windows)} windows", "", _fmt(rate),
                             ""])
            continue
        graph = r.get("cuda_graph")
        graphs = (f"{graph['graphs']} graphs, {graph['replays']} replays"
                  + (f", failed: {'; '.join(graph['failures'].values())[:80]}" if graph["failures"] else "")
                  if graph else "no")
        command = " ".join(r["command"][:3])
        body.append([command, f"{r.get('world_size')} x {r.get('device')}", r.get("backend", ""),
                     str(r.get("amp")), str(r.get("batch_per_process")), str(r.get("steps")), graphs,
                     _fmt(r.get("samples_per_s"), ".2f"), _fmt(r.get("peak_allocated_mb"), ".0f")])
    header = ["command", "processes", "backend", "AMP", "batch / process", "steps", "CUDA graphs", "samples/s",
              "peak MB (rank 0)"]
    return _table(header, body, {4, 5, 7, 8}) + [
        "", "samples/s: median over the logged windows after the first (warm-up and capture), all processes "
            "together. CUDA graphs: the steps replayed from graphs (`train.cuda_graph`; on a CPU the same step "
            "without a graph). `train_shipped`: the presets behind the shipped model, each on the few scenes "
            "that fill its batch."
    ] + profile_lines(out)


def profile_lines(out: Path) -> list[str]:
    """One line per burst that profiled its steps (``train.profile_steps``): where a step's time goes."""
    lines = []
    for stage in ("train_ae", "train_wm"):
        p = _read_json(out / stage / "run" / "profile.json")
        if p is None:
            continue
        phases = ", ".join(f"{name} {v['host_ms_per_step']:.1f} ms host / {v['device_ms_per_step']:.1f} ms device"
                           for name, v in p["phases"].items())
        gpu = (f", {p['kernels_per_step']:.0f} kernels and the GPU busy {p['gpu_busy_ms_per_step']:.1f} ms"
               if "kernels_per_step" in p else "")
        top = ", ".join(f"{t['name'][:40]} {t['ms_per_step']:.1f} ms" for t in p["top"][:3])
        lines.append(f"- {stage}: {p['wall_ms_per_step']:.1f} ms a step ({phases}){gpu}; most time: {top}.")
    return ["", "Where a step's time goes (rank 0, profiled steps; `run/profile.json`):", *lines] if lines else []


def tests_section(out: Path) -> list[str]:
    counts = junit_counts(out / "tests" / "junit.xml")
    if counts is None:
        return ["No CUDA test results (tests/junit.xml missing)."]
    ran = counts["tests"] - counts["skipped"]
    return [f"`pytest -m cuda`: {ran} ran, {counts['failures']} failed, {counts['errors']} errors, "
            f"{counts['skipped']} skipped."]


def report(out: Path, peak_tflops: float | None = None, peak_gbps: float | None = None) -> str:
    env = _read_json(out / "env" / "env.json") or {}
    gpu = env["gpus"][0]["name"] if env.get("gpus") else None
    found = peaks_for(gpu)
    peaks = found[1] if found else None
    if peak_tflops or peak_gbps:
        base = peaks or (0.0, 0.0, 0.0, 0.0)
        peaks = (peak_tflops or base[0], base[1], base[2], peak_gbps or base[HBM])
        peaks = peaks if peaks[0] and peaks[HBM] else None
    parts = [
        header_section(out), ["", "### Stages", ""], stages_section(out), ["", "### CUDA tests", ""],
        tests_section(out), ["", "### Op benchmarks: fused vs reference", ""], ops_section(out, peaks),
        ["", "### Forecasting step", ""], forecast_section(out), ["", "### Training bursts", ""],
        training_section(out),
    ]
    return "\n".join(line for part in parts for line in part) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.gpu.report", description=__doc__.splitlines()[0])
    parser.add_argument("outdir", type=Path, help="folder written by benchmarks/gpu/run.sh")
    parser.add_argument("--peak-tflops", type=float, help="fp32 compute roof (TFLOP/s) instead of the table's")
    parser.add_argument("--peak-gbps", type=float, help="memory roof (GB/s) instead of the table's")
    args = parser.parse_args(argv)
    if not args.outdir.is_dir():
        parser.error(f"{args.outdir} is not a folder")
    print(report(args.outdir, args.peak_tflops, args.peak_gbps), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
