"""The GPU check in one command: ``python -m benchmarks.gpu.run OUTDIR`` (or ``run.sh``).

Stages, each with its own time limit and each run whatever happened before it:

  env       ``nvidia-smi -L``, Python / torch / CUDA / cuDNN / NCCL versions
  build     the extension with CUDA (``setup.py build_ext --inplace``, sm_90 by default,
            parallel), then ``t3fast.build_info()``
  tests     ``pytest -m cuda tests``: parity of every op and mode against the references,
            float16 / bfloat16, opcheck, compile (junit XML and log)
  ops       op benchmarks, fused against reference in one pytest-benchmark JSON, with the
            FLOPs and bytes of each workload
  forecast  the whole forecast (encoding included) of the shipped model and the untrained
            small and paper sizes: eager, reference ops, CUDA graph, torch.compile at batch 1,
            eager at batch 64; FPS and peak memory
  demo      ``t3fast demo`` (what ``make demo`` runs) on the device, its metrics held against the
            committed CPU run's (``benchmarks/results/wm-test-metrics.json``, the same windows)
  train_ae  a timed burst of ``t3fast train-ae --config paper`` under torchrun (NCCL, AMP)
  train_wm  the same for ``t3fast train-wm --config paper``, its steps replayed from CUDA graphs
            on one process, then a shorter burst of eager steps to hold them against
  train_shipped  a short burst of each preset behind the shipped model (stage 2, box motion,
            route planner, motion head, autoencoder), one process each

Everything goes under OUTDIR: one folder per stage with its logs and results, and
``summary.json`` / ``summary.md`` saying which stages passed. The exit status is 0 only when
every stage passed. ``--device cpu --quick`` is the dry run of the same script: tiny sizes,
gloo, no build, a few steps; it checks the script, not the kernels.

Time: each stage's limit is cut so that the whole run ends within ``--budget`` seconds while
every later stage keeps at least its floor; a stage past its limit is killed (its process
group: SIGTERM, then SIGKILL) and marked ``timeout``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HERE = "benchmarks/gpu"  # the helpers run as scripts from ROOT: no package name to shadow
PY = sys.executable


@dataclass
class Step:
    """One command of a stage; its output (stdout and stderr) goes to ``<stage>/<name>.log``."""

    name: str
    argv: list[str]
    env: dict[str, str] = field(default_factory=dict)


@dataclass
class Stage:
    name: str
    title: str
    limit_s: float  # nominal time limit
    floor_s: float  # time kept for it while earlier stages run
    steps: Callable[[Context, Path], list[Step]]
    check: Callable[[Context, Path], tuple[bool, str]] | None = None


@dataclass
class Context:
    out: Path
    device: str
    quick: bool
    arch: str
    jobs: int
    nproc: int
    compilers: dict[str, str] = field(default_factory=dict)  # CC / CXX of the build; empty: the environment's

    @property
    def cuda(self) -> bool:
        return self.device == "cuda"

    @property
    def env(self) -> dict[str, str]:
        """Environment of every step. On the CPU one OpenMP thread per process: the dry run
        shares its cores, and spinning OpenMP teams on oversubscribed cores run 10-100x slower."""
        return {} if self.cuda else {"OMP_NUM_THREADS": "1"}


# ---- the stages ------------------------------------------------------------------------------


def _env_steps(ctx: Context, d: Path) -> list[Step]:
    steps = []
    if shutil.which("nvidia-smi"):
        steps.append(Step("nvidia-smi", ["nvidia-smi", "-L"]))
        query = "name,memory.total,driver_version,clocks.max.sm,power.limit"
        steps.append(Step("nvidia-smi-query", ["nvidia-smi", f"--query-gpu={query}", "--format=csv"]))
    elif ctx.cuda:
        steps.append(Step("nvidia-smi", [PY, "-c", "import sys; sys.exit('nvidia-smi not found')"]))
    steps.append(Step("versions", [PY, f"{HERE}/probe.py", "env", "--out", str(d / "env.json")]
                      + (["--expect-cuda"] if ctx.cuda else [])))
    return steps


def _build_steps(ctx: Context, d: Path) -> list[Step]:
    steps = []
    if ctx.cuda:
        env = {"FORCE_CUDA": "1", "TORCH_CUDA_ARCH_LIST": ctx.arch, "MAX_JOBS": str(ctx.jobs), **ctx.compilers}
        steps.append(Step("build_ext", [PY, "setup.py", "build_ext", "--inplace"], env))
    steps.append(Step("build_info", [PY, f"{HERE}/probe.py", "build", "--out", str(d / "build_info.json")]
                      + (["--expect-cuda"] if ctx.cuda else [])))
    return steps


def _test_steps(ctx: Context, d: Path) -> list[Step]:
    return [Step("pytest", [PY, "-m", "pytest", "-m", "cuda", "tests", "-q", "-p", "no:cacheprovider",
                            f"--junitxml={d / 'junit.xml'}", "-o", "junit_family=xunit2"])]


def _check_tests(ctx: Context, d: Path) -> tuple[bool, str]:
    counts = junit_counts(d / "junit.xml")
    if counts is None:
        return False, "no junit.xml"
    ran = counts["tests"] - counts["skipped"]
    detail = f"{ran} ran, {counts['failures']} failed, {counts['errors']} errors, {counts['skipped']} skipped"
    if counts["failures"] or counts["errors"]:
        return False, detail
    if ctx.cuda and ran == 0:
        return False, detail + " (nothing ran on the GPU)"
    return True, detail


def _ops_steps(ctx: Context, d: Path) -> list[Step]:
    env = {"T3FAST_BENCH_DEVICE": ctx.device, "T3FAST_BENCH_QUICK": "1" if ctx.quick else "0"}
    return [Step("pytest-benchmark", [PY, "-m", "pytest", "benchmarks/test_bench_ops.py", "--benchmark-only", "-q",
                                      "-p", "no:cacheprovider", f"--benchmark-json={d / 'benchmarks.json'}"], env)]


def _check_ops(ctx: Context, d: Path) -> tuple[bool, str]:
    path = d / "benchmarks.json"
    if not path.is_file():
        return False, "no benchmarks.json"
    data = json.loads(path.read_text())
    return True, f"{len(data.get('benchmarks', []))} benchmarks, {len(data.get('ratios', {}))} fused/reference pairs"


def _forecast_steps(ctx: Context, d: Path) -> list[Step]:
    """One process per group of modes: a failed CUDA-graph capture or compilation cannot spoil
    the others (within a group, eager runs first), and a time-out ends only the last group. The
    shipped model's rows come first (batch 1 and 64 eager and replayed from a CUDA graph, traced
    whole with the eager kernels in CUDA graphs, compiled by Inductor): the figures that matter;
    then the untrained sizes and the reference ops.
    Compilation takes minutes (the six-step rollout is traced whole), so each compiles in its own
    process. Every row but the paper size's compilation profiles one more call (``profile/``)."""
    groups = {"eager": ("tiny", "eager", 1)} if ctx.quick else {
        "shipped": ("shipped", "eager,cuda-graph", 1), "batch-64": ("shipped", "eager,cuda-graph", 64),
        "graphs-shipped": ("shipped", "compile-graphs", 1), "graphs-batch-64": ("shipped", "compile-graphs", 64),
        "compile-shipped": ("shipped", "compile", 1), "sizes": ("small,paper", "eager,cuda-graph", 1),
        "reference": ("shipped,small,paper", "eager-reference", 1), "compile-batch-64": ("shipped", "compile", 64),
        "compile-paper": ("paper", "compile", 1)}
    profiled = ("eager", "shipped", "batch-64", "graphs-shipped", "compile-shipped", "sizes", "reference",
                "compile-batch-64")
    steps = []
    for name, (sizes, modes, batch) in groups.items():
        argv = [PY, f"{HERE}/forecast.py", "--device", ctx.device, "--sizes", sizes, "--modes", modes,
                "--batch", str(batch), "--out", str(d / "results.jsonl")]
        argv += ["--profile", str(d / "profile")] if name in profiled else []
        steps.append(Step(f"forecast-{name}", argv + (["--quick"] if ctx.quick else [])))
    return steps


def _check_forecast(ctx: Context, d: Path) -> tuple[bool, str]:
    rows = read_jsonl(d / "results.jsonl")
    bad = [f"{r['size']}/{r['mode']}" for r in rows if "error" in r]
    detail = f"{len(rows) - len(bad)} of {len(rows)} rows measured" + (f"; failed: {', '.join(bad)}" if bad else "")
    return bool(rows) and not bad, detail


#: the CPU run the demo's metrics are held against: the same 40 windows of 10 test scenes
CPU_DEMO_METRICS = ROOT / "benchmarks" / "results" / "wm-test-metrics.json"
DEMO_TOLERANCE = 0.05  # mIoU points, Avg mIoU of every row both runs have


def _demo_steps(ctx: Context, d: Path) -> list[Step]:
    argv = [PY, "-m", "t3fast", "demo", "--out", str(d / "demo")]
    return [Step("demo", argv + (["--scenes", "1", "--stride", "29", "--pictures", "1"] if ctx.quick else []))]


def compare_demo(got: dict, want: dict) -> dict[str, float]:
    """Per row of both ``metrics.json`` mappings with an occupancy score: |Avg mIoU difference|."""
    return {name: abs(row["miou"]["avg"] - want[name]["miou"]["avg"]) for name, row in got.items()
            if isinstance(row.get("miou"), dict) and isinstance(want.get(name, {}).get("miou"), dict)}


def _check_demo(ctx: Context, d: Path) -> tuple[bool, str]:
    path = d / "demo" / "metrics.json"
    if not path.is_file():
        return False, "no demo/metrics.json"
    got = json.loads(path.read_text())
    if ctx.quick:
        return True, f"{len(got)} rows (a dry run: other windows than the CPU run's, not compared)"
    differences = compare_demo(got, json.loads(CPU_DEMO_METRICS.read_text()))
    (d / "comparison.json").write_text(json.dumps(differences, indent=1) + "\n")
    if not differences:
        return False, f"no row in common with {CPU_DEMO_METRICS.name}"
    worst = max(differences, key=differences.get)
    detail = (f"{len(differences)} rows against the CPU run, largest Avg mIoU difference "
              f"{differences[worst]:.3f} ({worst}; allowed {DEMO_TOLERANCE})")
    return differences[worst] <= DEMO_TOLERANCE, detail


def _burst_overrides(ctx: Context, d: Path) -> list[str]:
    """What every training burst sets: no evaluation or checkpoints, steps until the timer stops it."""
    return ["train.eval_every=0", "train.ckpt_every=0", "train.tensorboard=false", f"train.device={ctx.device}",
            "train.steps=100000", f"train.out_dir={d / 'run'}", f"train.log_every={1 if ctx.quick else 5}"]


def _train_overrides(ctx: Context, d: Path) -> list[str]:
    common = _burst_overrides(ctx, d)
    if ctx.quick:
        return common + ["train.batch_size=1", "loss.num_occupied=2000", "loss.num_near_free=1000",
                         "loss.num_far_free=500"]
    return common + ["train.profile_steps=3"]  # run/profile.json: where a step's time goes


def _torchrun(ctx: Context, d: Path, nproc: int, seconds: float, command: list[str], name: str = "torchrun",
              min_steps: int | None = None) -> Step:
    backend = "nccl" if ctx.cuda else "gloo"
    min_steps = min_steps or (2 if ctx.quick else 10)
    argv = [PY, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}",
            f"{HERE}/train_burst.py", "--backend", backend, "--seconds", str(seconds),
            "--min-steps", str(min_steps), "--result", str(d / "result.json"), "--", *command]
    env = {"OMP_NUM_THREADS": "1" if ctx.quick else "4"}
    if ctx.cuda:
        env["NCCL_DEBUG"] = os.environ.get("NCCL_DEBUG", "WARN")
    return Step(name, argv, env)


def _train_ae_steps(ctx: Context, d: Path) -> list[Step]:
    config = "small" if ctx.quick else "paper"
    data = ["data.train_scenes=1", "data.frames_per_scene=11"] if ctx.quick else ["data.train_scenes=2"]
    command = ["train-ae", "--config", config, *_train_overrides(ctx, d), *data]
    return [_torchrun(ctx, d, ctx.nproc, 1 if ctx.quick else 30, command)]


def _train_wm_steps(ctx: Context, d: Path) -> list[Step]:
    config = "small" if ctx.quick else "paper"
    steps = []
    ae = ctx.out / "train_ae" / "run" / "last.pt"
    if not ae.is_file():  # the stage-1 burst failed: a one-step stage-1 checkpoint of the same size
        ae = d / "ae" / "last.pt"
        frames = ["data.train_scenes=1", "data.frames_per_scene=11", "train.batch_size=1"]
        steps.append(Step("autoencoder", [PY, "-m", "t3fast", "train-ae", "--config", config, "train.steps=1",
                                          "train.eval_every=0", "train.tensorboard=false",
                                          f"train.device={ctx.device}", f"train.out_dir={ae.parent}", *frames]))
    frames = ["data.frames_per_scene=12"] if ctx.quick else []
    # the paper preset's path (quick: the small Delta forecaster's on it): labelled windows read
    # from the aligned cache, one 6-step rollout a sample
    command = ["train-wm", "--config", "small-delta" if ctx.quick else config, "--ae", str(ae), "data.train_scenes=1",
               f"data.cache_dir={d / 'cache'}", "data.cache_labels=true", "loss.rollout_steps=6", *frames]
    # its steps replayed from CUDA graphs on one process (quick: the stage-1 burst already ran two
    # under gloo), then a shorter burst of eager steps on the same cached windows to hold them against
    graphed = [*command, *_train_overrides(ctx, d), "train.cuda_graph=true"]
    eager = [*command, *_train_overrides(ctx, d / "eager"), "train.profile_steps=0", "train.cuda_graph=false"]
    # quick: past the eager warm-up steps and the capture (t3fast.training.graphed_step.WARMUP + 1)
    return [*steps, _torchrun(ctx, d, 1, 1 if ctx.quick else 30, graphed, min_steps=6 if ctx.quick else None),
            _torchrun(ctx, d / "eager", 1, 1 if ctx.quick else 15, eager, name="eager")]


#: the runs behind the shipped world model (``t3fast train --recipe wm-small``), by what they
#: train, most telling first: each preset's command, on the fewest scenes that fill its batch
SHIPPED = {
    "wm": ["train-wm", "--config", "small", "--ae", "wm-small", "data.train_scenes=1"],
    # the same steps replayed from CUDA graphs (one per mirror and flips drawn, up to 16)
    "wm-graphed": ["train-wm", "--config", "small", "--ae", "wm-small", "data.train_scenes=1", "train.cuda_graph=true"],
    "box": ["train-box-motion", "--config", "small", "data.train_scenes=4", "data.select_scenes=1"],
    "plan": ["train-planner", "--config", "small", "data.train_scenes=3"],
    "motion": ["train-motion", "--config", "small", "data.train_scenes=3"],
    "ae": ["train-ae", "--config", "small", "data.train_scenes=1"],
}


def _train_shipped_steps(ctx: Context, d: Path) -> list[Step]:
    """A short burst of each preset behind the shipped model, at its own batch and precision,
    its cached windows built first (outside the timed steps; quick: 12 frames, batch 1)."""
    steps = []
    for name, command in SHIPPED.items():
        data = [f"data.cache_dir={d / 'cache'}"] if name != "ae" else []
        data += ["data.frames_per_scene=12", "train.batch_size=1"] if ctx.quick else []
        argv = [*command, *_burst_overrides(ctx, d / name), *data]
        seconds = 1 if ctx.quick else 12 if "train.cuda_graph=true" in command else 6  # past its captures
        steps.append(_torchrun(ctx, d / name, 1, seconds, argv, name=name))
    return steps


def _check_shipped(ctx: Context, d: Path) -> tuple[bool, str]:
    rates = {}
    for name in SHIPPED:
        path = d / name / "result.json"
        rates[name] = json.loads(path.read_text()).get("samples_per_s") if path.is_file() else None
    detail = ", ".join(f"{name} {rate:.1f}" if rate else f"{name} -" for name, rate in rates.items())
    return all(rates.values()), f"samples/s: {detail}"


def _check_train(ctx: Context, d: Path) -> tuple[bool, str]:
    path = d / "result.json"
    if not path.is_file():
        return False, "no result.json"
    r = json.loads(path.read_text())
    rate = r.get("samples_per_s")
    if not rate:
        return False, f"no throughput logged ({r.get('steps')} steps)"
    detail = (f"{rate:.2f} samples/s, {r.get('steps')} steps, world {r.get('world_size')} {r.get('backend')}, "
              f"AMP {r.get('amp')}")
    graph = r.get("cuda_graph")
    if graph is not None:
        failed = "; ".join(f"{k}: {v}" for k, v in graph["failures"].items())
        detail += f", {graph['graphs']} CUDA graphs, {graph['replays']} replays"
        detail += f" (failed: {failed})" if failed else ""
    eager = d / "eager" / "result.json"
    if eager.is_file():
        rate = json.loads(eager.read_text()).get("samples_per_s")
        detail += f"; eager {rate:.2f} samples/s" if rate else "; eager: no throughput logged"
    return r.get("returncode") == 0, detail


def _check_json(name: str) -> Callable[[Context, Path], tuple[bool, str]]:
    def check(ctx: Context, d: Path) -> tuple[bool, str]:
        path = d / name
        if not path.is_file():
            return False, f"no {name}"
        info = json.loads(path.read_text())
        if name == "env.json":
            gpus = ", ".join(g["name"] for g in info.get("gpus", [])) or "no GPU"
            return True, f"torch {info.get('torch')}, CUDA {info.get('torch_cuda')}, {gpus}"
        return True, f"cuda={info.get('cuda')} cuda_version={info.get('cuda_version')}"

    return check


STAGES = [
    Stage("env", "environment", 60, 10, _env_steps, _check_json("env.json")),
    Stage("build", "CUDA build", 240, 30, _build_steps, _check_json("build_info.json")),
    Stage("tests", "CUDA tests", 150, 45, _test_steps, _check_tests),
    Stage("ops", "op benchmarks", 180, 45, _ops_steps, _check_ops),  # decode in fp32, TF32 and bf16
    Stage("forecast", "whole forecast", 270, 60, _forecast_steps, _check_forecast),
    Stage("demo", "t3fast demo", 240, 90, _demo_steps, _check_demo),
    Stage("train_ae", "train-ae burst", 80, 45, _train_ae_steps, _check_train),
    Stage("train_wm", "train-wm burst", 130, 70, _train_wm_steps, _check_train),
    # no floor: it runs in what the stages before it leave (the forecast's time comes first)
    Stage("train_shipped", "shipped presets' training", 140, 0, _train_shipped_steps, _check_shipped),
]


def build_compilers(cxx: str | None) -> dict[str, str]:
    """CC and CXX for the build. The distribution's g++ by default: an image may point CXX at a
    wrapper whose builds crash (in std::ostream) the moment a kernel formats a number into an
    error message, a C++ runtime mismatch that the build stage's error check catches."""
    if cxx is None:
        cxx = "/usr/bin/g++" if Path("/usr/bin/g++").is_file() else None
    if cxx is None:
        return {}
    cc = Path(cxx).with_name(Path(cxx).name.replace("g++", "gcc").replace("c++", "cc"))
    return {"CXX": cxx, "CC": str(cc)} if cc.is_file() else {"CXX": cxx}


# ---- running ---------------------------------------------------------------------------------


def junit_counts(path: Path) -> dict[str, int] | None:
    """tests / failures / errors / skipped summed over the test suites of a junit XML file."""
    if not path.is_file():
        return None
    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else root.findall("testsuite")
    keys = ("tests", "failures", "errors", "skipped")
    return {k: sum(int(s.get(k, 0)) for s in suites) for k in keys}


def read_jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def run_step(step: Step, log: Path, timeout: float, extra_env: dict[str, str] | None = None) -> dict:
    """Run ``step`` in its own process group with output to ``log``; kill the group on timeout."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    env.update(extra_env or {})
    env.update(step.env)
    start = time.perf_counter()
    result = {"name": step.name, "argv": step.argv, "env": step.env, "log": log.name, "timed_out": False}
    with log.open("w") as f:
        f.write(f"$ {' '.join(step.argv)}\n# env: {step.env}\n")
        f.flush()
        try:
            proc = subprocess.Popen(step.argv, cwd=ROOT, env=env, stdout=f, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True)
        except OSError as exc:
            f.write(f"cannot start: {exc}\n")
            result.update(returncode=127, seconds=0.0)
            return result
        try:
            rc = proc.wait(timeout=max(timeout, 1))
        except subprocess.TimeoutExpired:
            result["timed_out"] = True
            _kill_group(proc)
            rc = proc.returncode
            f.write(f"\n# killed after {timeout:.0f} s (stage time limit)\n")
    result.update(returncode=rc, seconds=round(time.perf_counter() - start, 2))
    return result


def _kill_group(proc: subprocess.Popen) -> None:
    for sig, grace in ((signal.SIGTERM, 5), (signal.SIGKILL, 5)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass
        try:
            proc.wait(timeout=grace)
            return
        except subprocess.TimeoutExpired:
            continue


def run_stages(ctx: Context, stages: list[Stage], budget: float, log=print) -> dict:
    start = time.perf_counter()
    deadline = start + budget
    summary = {"device": ctx.device, "quick": ctx.quick, "budget_s": budget, "started": time.strftime("%F %T %Z"),
               "commit": _git_commit(), "stages": []}
    for i, stage in enumerate(stages):
        d = ctx.out / stage.name
        d.mkdir(parents=True, exist_ok=True)
        reserve = sum(s.floor_s for s in stages[i + 1 :])
        limit = min(stage.limit_s, deadline - time.perf_counter() - reserve)
        record = {"name": stage.name, "title": stage.title, "limit_s": round(limit, 1), "steps": []}
        stage_start = time.perf_counter()
        if limit < 5:
            record.update(status="skipped", detail="no time left in the budget", seconds=0.0)
        else:
            log(f"[{stage.name}] {stage.title} (limit {limit:.0f} s)")
            try:
                steps = stage.steps(ctx, d)
            except Exception as exc:  # a bug in a stage's set-up must not stop the others
                steps, record["detail"] = [], f"set-up failed: {type(exc).__name__}: {exc}"
            timed_out = failed = bool(record.get("detail"))
            for step in steps:
                left = limit - (time.perf_counter() - stage_start)
                if left < 1:
                    timed_out = True
                    break
                result = run_step(step, d / f"{step.name}.log", left, ctx.env)
                record["steps"].append(result)
                log(f"  {step.name}: rc {result['returncode']} in {result['seconds']:.1f} s"
                    + (" (time limit)" if result["timed_out"] else ""))
                timed_out |= result["timed_out"]
                failed |= result["returncode"] != 0
            ok, detail = False, record.get("detail", "")
            if stage.check is not None and not detail:
                try:
                    ok, detail = stage.check(ctx, d)
                except Exception as exc:
                    ok, detail = False, f"check failed: {type(exc).__name__}: {exc}"
            status = "passed" if ok and not failed and not timed_out else ("timeout" if timed_out else "failed")
            record.update(status=status, detail=detail, seconds=round(time.perf_counter() - stage_start, 1))
            log(f"  -> {status}: {detail}")
        summary["stages"].append(record)
        summary["total_s"] = round(time.perf_counter() - start, 1)
        _write_summary(ctx.out, summary)
    summary["passed"] = all(s["status"] == "passed" for s in summary["stages"])
    _write_summary(ctx.out, summary)
    return summary


def summary_markdown(summary: dict) -> str:
    lines = [f"GPU check on {summary['device']}{' (quick)' if summary['quick'] else ''}, "
             f"commit {summary.get('commit') or '?'}, {summary.get('total_s', 0):.0f} s "
             f"of a {summary['budget_s']:.0f} s budget", "",
             "| stage | status | time (s) | detail |", "|---|---|---:|---|"]
    for s in summary["stages"]:
        lines.append(f"| {s['name']} ({s['title']}) | {s['status']} | {s['seconds']:.0f} | {s.get('detail', '')} |")
    failed = [s["name"] for s in summary["stages"] if s["status"] != "passed"]
    lines += ["", "all stages passed" if not failed else f"not passed: {', '.join(failed)}"]
    return "\n".join(lines) + "\n"


def _write_summary(out: Path, summary: dict) -> None:
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "summary.md").write_text(summary_markdown(summary))


def drop_checkpoints(out: Path) -> None:
    """Delete what the training bursts wrote besides their logs (checkpoints, the triplane
    cache), so that the folder can be kept or committed as it is."""
    for stage in ("train_ae", "train_wm", "train_shipped"):
        for path in sorted((out / stage).glob("**/*.pt")):
            path.unlink()
        shutil.rmtree(out / stage / "cache", ignore_errors=True)


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks/gpu/run.sh", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[2:]))
    parser.add_argument("outdir", type=Path, help="where every log and result goes (created)")
    parser.add_argument("--device", choices=["cuda", "cpu"], default="cuda")
    parser.add_argument("--quick", action="store_true", help="tiny sizes and a few steps (the dry run)")
    parser.add_argument("--budget", type=float, default=None,
                        help="seconds for the whole run (default 540 on cuda, 400 with --quick)")
    parser.add_argument("--stages", default=",".join(s.name for s in STAGES),
                        help="comma-separated subset of the stages, in their fixed order")
    parser.add_argument("--arch", default=os.environ.get("TORCH_CUDA_ARCH_LIST", "9.0"),
                        help="TORCH_CUDA_ARCH_LIST of the build (default 9.0: H100 / H200)")
    parser.add_argument("--jobs", type=int, default=int(os.environ.get("MAX_JOBS", os.cpu_count() or 4)),
                        help="parallel compile jobs (MAX_JOBS)")
    parser.add_argument("--keep-checkpoints", action="store_true",
                        help="keep the bursts' checkpoints and triplane cache (hundreds of MB at paper size)")
    parser.add_argument("--cxx", default=None,
                        help="C++ compiler of the build (CC: the gcc beside it); default: /usr/bin/g++ where "
                             "there is one, else the environment's CXX")
    parser.add_argument("--nproc", type=int, default=None,
                        help="torchrun processes (default: every GPU; 2 on the CPU)")
    args = parser.parse_args(argv)

    wanted = args.stages.split(",")
    unknown = sorted(set(wanted) - {s.name for s in STAGES})
    if unknown:
        parser.error(f"unknown stages {unknown}")
    stages = [s for s in STAGES if s.name in wanted]
    nproc = args.nproc or (_gpu_count() if args.device == "cuda" else 2)
    budget = args.budget or (400.0 if args.quick else 540.0)
    out = args.outdir.resolve()
    out.mkdir(parents=True, exist_ok=True)
    ctx = Context(out=out, device=args.device, quick=args.quick, arch=args.arch, jobs=args.jobs, nproc=nproc,
                  compilers=build_compilers(args.cxx))
    summary = run_stages(ctx, stages, budget)
    if not args.keep_checkpoints:
        drop_checkpoints(out)
    text = summary_markdown(summary)
    print("\n" + text, end="")
    print(f"results in {out}; tables: python -m benchmarks.gpu.report {out}")
    return 0 if summary["passed"] else 1


def _gpu_count() -> int:
    """GPUs nvidia-smi lists (without importing torch here); 1 when it cannot tell."""
    if shutil.which("nvidia-smi"):
        try:
            out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30)
            count = sum(line.startswith("GPU ") for line in out.stdout.splitlines())
            if count:
                return count
        except (OSError, subprocess.TimeoutExpired):
            pass
    return 1


if __name__ == "__main__":
    sys.exit(main())
