"""The GPU check script (benchmarks/gpu): its CPU dry run end to end, the per-stage time limits,
and the report's roofline arithmetic."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.gpu import report as gpu_report
from benchmarks.gpu import run as gpu_run

ROOT = Path(__file__).resolve().parents[1]
STAGES = ["env", "build", "tests", "ops", "forecast", "demo", "train_ae", "train_wm", "train_shipped"]


@pytest.mark.slow
def test_dry_run_passes_every_stage_and_reports(tmp_path):
    """``run.sh OUT --device cpu --quick``: every stage passes on the CPU, the outputs the
    report reads are there, and the report prints every table."""
    out = tmp_path / "gpu"
    env = dict(os.environ, PYTHON=sys.executable)
    proc = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu" / "run.sh"), str(out), "--device", "cpu",
                           "--quick", "--budget", "500"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    summary = json.loads((out / "summary.json").read_text())
    statuses = {s["name"]: s["status"] for s in summary["stages"]}
    logs = "\n".join(f"--- {p.relative_to(out)}\n{p.read_text()[-1500:]}" for p in sorted(out.glob("*/*.log"))
                     if "passed" != statuses.get(p.parent.name))
    assert statuses == dict.fromkeys(STAGES, "passed"), proc.stdout[-3000:] + logs
    assert proc.returncode == 0
    assert (out / "summary.md").read_text().strip().endswith("all stages passed")
    for path in ["env/env.json", "build/build_info.json", "tests/junit.xml", "ops/benchmarks.json",
                 "forecast/results.jsonl", "demo/demo/metrics.json", "train_ae/result.json", "train_wm/result.json"]:
        assert (out / path).is_file(), path
    bench = json.loads((out / "ops" / "benchmarks.json").read_text())
    assert all({"flops", "bytes"} <= set(b["extra_info"]) for b in bench["benchmarks"])
    profiled = json.loads((out / "forecast" / "profile" / "tiny-eager-b1.json").read_text())
    assert profiled["ops"] > 100 and profiled["top"][0]["ms"] > 0  # on a CPU: the ops, by self time
    ae = json.loads((out / "train_ae" / "result.json").read_text())
    assert ae["world_size"] == 2 and ae["ddp"] and ae["samples_per_s"] > 0
    wm = json.loads((out / "train_wm" / "result.json").read_text())
    assert wm["cuda_graph"]["replays"] > 0 and not wm["cuda_graph"]["failures"]  # on a CPU: no graph, the same step
    assert json.loads((out / "train_wm" / "eager" / "result.json").read_text())["cuda_graph"] is None
    for name, command in gpu_run.SHIPPED.items():  # each preset behind the shipped model trained a few steps
        burst = json.loads((out / "train_shipped" / name / "result.json").read_text())
        assert burst["command"][:3] == command[:3] and burst["steps"] >= 2 and burst["samples_per_s"] > 0, name

    text = subprocess.run([sys.executable, "-m", "benchmarks.gpu.report", str(out)], cwd=ROOT, capture_output=True,
                          text=True, check=True, timeout=60).stdout
    for heading in ["### Stages", "### CUDA tests", "### Op benchmarks", "### Forecasting step", "### Training bursts"]:
        assert heading in text
    assert "| decode grid fwd paper |" in text and "| tiny | eager |" in text
    assert "| train-ae --config small | 2 x cpu | gloo |" in text
    assert "| train-box-motion --config small | 1 x cpu | gloo |" in text


def test_a_stage_past_its_limit_is_killed_and_the_next_still_runs(tmp_path):
    def sleeper(ctx, d):
        return [gpu_run.Step("sleep", [sys.executable, "-c", "import time; time.sleep(60)"])]

    def failing(ctx, d):
        return [gpu_run.Step("fail", [sys.executable, "-c", "raise SystemExit(3)"])]

    def fine(ctx, d):
        (d / "ok").write_text("ok")
        return [gpu_run.Step("true", [sys.executable, "-c", "print('hello')"])]

    stages = [
        gpu_run.Stage("slow", "sleeps", 6, 1, sleeper),
        gpu_run.Stage("broken", "fails", 10, 1, failing),
        gpu_run.Stage("fine", "passes", 10, 1, fine, lambda ctx, d: ((d / "ok").is_file(), "ok file")),
    ]
    ctx = gpu_run.Context(out=tmp_path, device="cpu", quick=True, arch="9.0", jobs=1, nproc=1)
    summary = gpu_run.run_stages(ctx, stages, budget=60, log=lambda *a: None)
    statuses = {s["name"]: s["status"] for s in summary["stages"]}
    assert statuses == {"slow": "timeout", "broken": "failed", "fine": "passed"}
    assert not summary["passed"]
    assert "hello" in (tmp_path / "fine" / "true.log").read_text()
    assert json.loads((tmp_path / "summary.json").read_text())["stages"][2]["status"] == "passed"


def test_budget_keeps_the_floor_of_later_stages(tmp_path):
    seen = []

    def record(ctx, d):
        seen.append(d.name)
        return []

    stages = [gpu_run.Stage(f"s{i}", "", 100, 20, record, lambda ctx, d: (True, "")) for i in range(3)]
    ctx = gpu_run.Context(out=tmp_path, device="cpu", quick=True, arch="9.0", jobs=1, nproc=1)
    summary = gpu_run.run_stages(ctx, stages, budget=50, log=lambda *a: None)
    limits = [s["limit_s"] for s in summary["stages"]]
    assert limits[0] <= 10.0 and limits[1] <= 30.0  # 50 s minus the floors of the later stages
    assert seen == ["s0", "s1", "s2"]


def test_report_roofline_fraction(tmp_path):
    """A compute-bound and a memory-bound workload on an H200: fraction of the lower roof."""
    (tmp_path / "env").mkdir()
    (tmp_path / "env" / "env.json").write_text(json.dumps({"gpus": [{"name": "NVIDIA H200"}], "torch": "x"}))
    (tmp_path / "ops").mkdir()

    def bench(group, impl, median, flops, nbytes):
        return {"group": group, "params": {"impl": impl}, "stats": {"median": median},
                "extra_info": {"flops": flops, "bytes": nbytes}}

    benchmarks = [
        bench("mlp", "fused", 1e-3, 33.5e9, 1e6),  # 33.5 TFLOP/s, intensity 33500: half the 67 TFLOP/s roof
        bench("mlp", "reference", 1e-2, 33.5e9, 1e6),
        bench("copy", "fused", 1e-3, 1e6, 2.4e9),  # 2.4 TB/s of 4.8: half the memory roof
        bench("copy", "reference", 2e-3, 1e6, 2.4e9),
    ]
    (tmp_path / "ops" / "benchmarks.json").write_text(json.dumps({"benchmarks": benchmarks}))
    text = gpu_report.report(tmp_path)
    mlp = next(line for line in text.splitlines() if line.startswith("| mlp |"))
    copy = next(line for line in text.splitlines() if line.startswith("| copy |"))
    assert "| 10.0x |" in mlp and "| compute | 50.0 |" in mlp
    assert "| 2.0x |" in copy and "| memory | 50.0 |" in copy
    assert "67 TFLOP/s dense fp32" in text and "4.8 TB/s HBM" in text
    assert gpu_report.peaks_for("NVIDIA H100 80GB HBM3")[0] == "H100"
    assert gpu_report.peaks_for("NVIDIA H100 PCIe")[0] == "H100 PCIe"


def test_the_demo_is_held_against_the_cpu_runs_metrics(tmp_path, monkeypatch):
    """Every row both runs score is compared; one beyond the tolerance fails the stage, naming it."""
    want = {"t3former": {"miou": {"avg": 26.54}}, "copy_paste": {"miou": {"avg": 10.40}},
            "constant_turn_rate": {"miou": None}}
    cpu = tmp_path / "cpu.json"
    cpu.write_text(json.dumps(want))
    monkeypatch.setattr(gpu_run, "CPU_DEMO_METRICS", cpu)
    ctx = gpu_run.Context(out=tmp_path, device="cuda", quick=False, arch="9.0", jobs=1, nproc=1)
    (tmp_path / "demo").mkdir()
    got = {"t3former": {"miou": {"avg": 26.56}}, "copy_paste": {"miou": {"avg": 10.40}},
           "constant_turn_rate": {"miou": None}, "t3former_gt_ego": {"miou": {"avg": 61.0}}}
    (tmp_path / "demo" / "metrics.json").write_text(json.dumps(got))
    ok, detail = gpu_run._check_demo(ctx, tmp_path)
    assert ok and detail.startswith("2 rows against the CPU run, largest Avg mIoU difference 0.020 (t3former")
    got["copy_paste"]["miou"]["avg"] = 10.50
    (tmp_path / "demo" / "metrics.json").write_text(json.dumps(got))
    ok, detail = gpu_run._check_demo(ctx, tmp_path)
    assert not ok and "0.100 (copy_paste; allowed 0.05)" in detail



def test_the_report_says_where_a_profiled_training_step_s_time_goes(tmp_path):
    import torch

    from t3fast.training.step_profile import SKIP, StepProfile

    run = tmp_path / "train_wm" / "run"
    run.mkdir(parents=True)
    profile = StepProfile(run / "profile.json", 2, torch.device("cpu"))
    weight = torch.randn(64, 64, requires_grad=True)
    for _ in range(SKIP + 2):
        profile.step_begin()
        with profile.phase("forward"):
            loss = (torch.randn(32, 64) @ weight).square().mean()
        with profile.phase("backward"):
            loss.backward()
        profile.step_done()
    lines = gpu_report.profile_lines(tmp_path)
    assert len(lines) == 3 and lines[2].startswith("- train_wm: ") and "forward" in lines[2] and "backward" in lines[2]
