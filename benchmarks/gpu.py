"""The one-shot GPU benchmark: everything tt wants to know from a GPU, in one call of <= 8 minutes.

Sections, each with its own time budget (a section that runs out of budget stops and says
which configurations it skipped):

1. tests: ``python -m pytest -m gpu`` (the CUDA half of the device-parametrised tests);
2. rollout: world-steps/s of tt's fused Warp kernels against MuJoCo-Warp on the nominal
   ViperX (one topology, one structure: the batch the MuJoCo-Warp nightly measures on its
   Franka), N = 1k ... 64k worlds, CUDA graphs on and off;
3. training: DiT training throughput (samples/s = windows per second) for the mini and small
   models, bf16 autocast, batch 256 ... 1024, ``torch.compile`` on and off, through
   `tt.dit.train.train` itself on windows of ViperX episodes the Warp sim generated;
4. sampling: wall time of 1 / 16 / 128 candidates x 20 / 100 DDIM steps with the shipped
   checkpoint (`tt.guidance.zeroth.CandidateSampler`, Zeroth-Order's sampler);
5. online: ``tt train --online`` steps/s (mini, both tasks) with the episodes generated on the
   device, and the share of the time spent generating.

``--device cpu --quick`` runs the same code paths with tiny sizes on the CPU (no
``torch.compile``: inductor's C++ compile alone outlasts the quick budget), which
`tests/test_benchmark_gpu.py` runs. Writes ``--out`` (default ``benchmarks/results/gpu.md``)
with the machine, date and load, and prints one ``RESULT {json}`` line per measurement.

Usage: ``python benchmarks/gpu.py [--device cuda] [--out FILE] [--quick] [--sections ...]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "gpu.md"
SECTIONS = ("tests", "rollout", "training", "sampling", "online")


@dataclass
class Plan:
    """Sizes and time budgets [s] of every section."""

    budget: dict[str, float]
    worlds: tuple[int, ...]
    rollout_steps: int
    train_sizes: tuple[str, ...]
    train_batches: tuple[int, ...]
    train_steps: int
    compile_modes: tuple[bool, ...]
    candidates: tuple[int, ...]
    ddim_steps: tuple[int, ...]
    online_steps: int
    online_batch: int
    online_size: str
    online_designs: int
    test_args: tuple[str, ...] = field(default=("-m", "gpu", "-q", "-p", "no:cacheprovider"))


FULL = Plan(
    budget={"tests": 150, "rollout": 110, "training": 120, "sampling": 40, "online": 50},
    worlds=(1024, 4096, 16384, 32768, 65536),
    rollout_steps=50,
    train_sizes=("mini", "small"),
    train_batches=(256, 512, 1024),
    train_steps=12,
    compile_modes=(False, True),
    candidates=(1, 16, 128),
    ddim_steps=(20, 100),
    online_steps=60,
    online_batch=256,
    online_size="mini",
    online_designs=256,
)
QUICK = Plan(
    budget={"tests": 60, "rollout": 40, "training": 40, "sampling": 30, "online": 40},
    worlds=(16, 64),
    rollout_steps=4,
    train_sizes=("tiny",),
    train_batches=(8,),
    train_steps=3,
    compile_modes=(False,),
    candidates=(1, 2),
    ddim_steps=(2,),
    online_steps=2,
    online_batch=4,
    online_size="tiny",
    online_designs=2,
    test_args=("-m", "gpu", "-q", "-p", "no:cacheprovider", "tests/test_rewards.py", "-k", "device"),
)


def _sync(device: str) -> None:
    import torch
    import warp as wp

    if device.startswith("cuda"):
        wp.synchronize_device(device)
        torch.cuda.synchronize()


def _emit(rows: list[dict], row: dict) -> None:
    rows.append(row)
    print("RESULT " + json.dumps(row), flush=True)


class Clock:
    """A section's budget: `left()` seconds remain; `over()` once spent. A section always runs
    its first configuration (of each backend and graph mode, for the rollout), so every code
    path runs once even on a slow machine; the budget cuts the larger ones."""

    def __init__(self, seconds: float):
        self.end = time.monotonic() + seconds

    def left(self) -> float:
        return self.end - time.monotonic()

    def over(self) -> bool:
        return self.left() <= 0


# ------------------------------------------------------------------------------ sections
def run_tests(plan: Plan, device: str, clock: Clock, rows: list[dict]) -> str:
    import importlib.util

    cmd = [sys.executable, "-m", "pytest", *plan.test_args]
    if device.startswith("cuda") and importlib.util.find_spec("xdist") is not None:
        # Each test module compiles its own Warp modules for CUDA: spread them over the cores.
        cmd += ["-n", str(min(8, os.cpu_count() or 1))]
    t0 = time.perf_counter()
    try:
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=max(5.0, clock.left()))
        tail = (res.stdout + res.stderr).strip().splitlines()
        summary, code = (tail[-1] if tail else ""), res.returncode
    except subprocess.TimeoutExpired:
        summary, code = f"stopped at the section's budget ({plan.budget['tests']:.0f} s)", -1
    _emit(
        rows,
        {
            "section": "tests",
            "command": " ".join(cmd[1:]),
            "exit": code,
            "summary": summary,
            "seconds": time.perf_counter() - t0,
        },
    )
    return f"`{' '.join(['python', *cmd[1:]])}`: exit {code}; {summary}\n"


def run_rollout(plan: Plan, device: str, clock: Clock, rows: list[dict]) -> str:
    from tt.kernels.model import build_tree_model
    from tt.kernels.rollout import motion_arrays, rollout_tree
    from tt.sim.controller import IKConfig
    from tt.sim.designs import get_space
    from tt.sim.mjwarp_backend import mjwarp_rollout
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.motions.base import Motion

    space = get_space("viperx")
    model = space.model(space.nominal())
    base = for_space([resolve_motion("toss")], "viperx")[0]
    T = min(plan.rollout_steps, base.steps)
    motion = Motion(base.name, base.pos[:T], base.quat[:T], base.dt)
    config = IKConfig()
    substeps = config.substeps(model)
    tree = build_tree_model([model], space.ee_sites(), device=device)  # one entry: world w reads entry 0
    marrays = motion_arrays(motion.pos[None], motion.quat[None], [T], device=device)

    def warp(n: int, graph: bool) -> None:
        rollout_tree(tree, marrays, n, T, **config.rollout_args(), device=device, graph=graph)

    def mjwarp(n: int, graph: bool) -> None:
        # n worlds of one structure: the design on n copies of the motion.
        mjwarp_rollout([model], [motion] * n, config=config, device=device, graph=graph)

    lines = [
        "| backend | graph | " + " | ".join(f"N = {n:,}" for n in plan.worlds) + " |",
        "|---|---|" + "---:|" * len(plan.worlds),
    ]
    skipped = []
    for name, fn in (("warp (tt's fused kernels)", warp), ("mjwarp", mjwarp)):
        for graph in (True, False):
            cells = []
            fn(plan.worlds[0], graph)  # compile and load outside the timing
            _sync(device)
            for n in plan.worlds:
                if clock.over() and n != plan.worlds[0]:
                    cells.append("budget")
                    skipped.append(f"{name} graph={graph} N={n}")
                    continue
                t0 = time.perf_counter()
                fn(n, graph)
                _sync(device)
                seconds = time.perf_counter() - t0
                rate = n * T * substeps / seconds
                cells.append(f"{rate / 1e6:.3g} M")
                _emit(
                    rows,
                    {
                        "section": "rollout",
                        "backend": name.split()[0],
                        "graph": graph,
                        "worlds": n,
                        "control_steps": T,
                        "world_steps_per_s": rate,
                        "seconds": seconds,
                    },
                )
            lines.append(f"| {name} | {'on' if graph else 'off'} | " + " | ".join(cells) + " |")
    note = (
        f"\nViperX nominal design on `{motion.name}` cut to {T} control steps ({substeps} physics steps each), "
        "closed loop (DiffIK + physics), one batch per N; world-steps/s = N x physics steps / wall time, "
        "compile excluded, model building and start posture included. warp: `rollout_tree` with one model entry "
        "that every world reads; graph on = the whole rollout replayed as one captured graph. mjwarp: "
        "`mjwarp_rollout` as tt runs it (MuJoCo-Warp physics, tt's batched IK kernel, whose tree model is built "
        "per world in Python: a visible share at large N); graph on = each control step's physics replayed "
        "as one captured graph.\n"
    )
    if skipped:
        note += f"\nNot run (section budget): {', '.join(skipped)}.\n"
    return "\n".join(lines) + "\n" + note


def _viperx_episodes(device: str, designs: int, seed: int = 0):
    """Episode tokens of `designs` random ViperX designs x 4 training motions, rolled out on
    `device` (one refresh of the online source)."""
    from tt.dit.online import OnlineConfig, OnlineTokenSource

    src = OnlineTokenSource(
        OnlineConfig(designs=designs, motions=4, refresh_every=10**9, buffer=1, seed=seed), device=device
    )
    src.start_step(0)
    return src


def run_training(plan: Plan, device: str, clock: Clock, rows: list[dict]) -> str:
    import torch

    from tt.dit.train import TrainConfig, train

    source = _viperx_episodes(device, designs=max(8, plan.online_designs // 4))
    lines = ["| model | batch | torch.compile | samples/s | s / step |", "|---|---:|---|---:|---:|"]
    skipped = []
    for size in plan.train_sizes:
        for batch in plan.train_batches:
            for compiled in plan.compile_modes:
                if clock.over() and rows[-1]["section"] == "training":
                    skipped.append(f"{size} batch {batch} compile={compiled}")
                    continue
                stamps = []
                with tempfile.TemporaryDirectory() as out:
                    cfg = TrainConfig(
                        out=out,
                        task="both",
                        size=size,
                        steps=plan.train_steps,
                        batch_size=batch,
                        device=device,
                        checkpoint_every=10**9,
                        resume=False,
                        warmup_steps=2,
                        bf16=True,
                        compile=compiled,
                    )
                    train(
                        cfg,
                        episodes=source,
                        on_step=lambda step, loss: (_sync(device), stamps.append(time.perf_counter())),
                    )
                # The first third of the steps warms up (cuDNN / inductor compiles, allocator).
                first = max(1, len(stamps) // 3)
                seconds = (stamps[-1] - stamps[first - 1]) / (len(stamps) - first)
                rate = batch / seconds
                lines.append(f"| {size} | {batch} | {'on' if compiled else 'off'} | {rate:,.0f} | {seconds:.3f} |")
                _emit(
                    rows,
                    {
                        "section": "training",
                        "size": size,
                        "batch": batch,
                        "compile": compiled,
                        "bf16": True,
                        "samples_per_s": rate,
                        "seconds_per_step": seconds,
                    },
                )
                if device.startswith("cuda"):
                    torch.cuda.empty_cache()
    note = (
        "\nOne training step = one optimizer step over `batch` windows of 8 steps (half robot, half control), "
        f"bf16 autocast on CUDA; timed over the last two thirds of {plan.train_steps} steps.\n"
    )
    if skipped:
        note += f"\nNot run (section budget): {', '.join(skipped)}.\n"
    return "\n".join(lines) + "\n" + note


def run_sampling(plan: Plan, device: str, clock: Clock, rows: list[dict]) -> str:
    from tt.dit.checkpoint import default_checkpoint, load_model
    from tt.guidance.zeroth import CandidateSampler
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.rewards import get_reward

    trained = load_model(default_checkpoint("viperx"), device=device)
    sampler = CandidateSampler(trained, device)
    motion = for_space([resolve_motion("toss")], "viperx")
    reward = get_reward("tracking", "viperx")
    sampler.run(motion, reward, 1, num_steps=2)  # warm-up
    lines = ["| candidates | DDIM steps | seconds |", "|---:|---:|---:|"]
    skipped = []
    for n in plan.candidates:
        for steps in plan.ddim_steps:
            if clock.over() and rows[-1]["section"] == "sampling":
                skipped.append(f"{n} x {steps}")
                continue
            _sync(device)
            t0 = time.perf_counter()
            sampler.run(motion, reward, n, num_steps=steps)
            _sync(device)
            seconds = time.perf_counter() - t0
            lines.append(f"| {n} | {steps} | {seconds:.3f} |")
            _emit(rows, {"section": "sampling", "candidates": n, "ddim_steps": steps, "seconds": seconds})
    note = (
        f"\nShipped checkpoint `{default_checkpoint('viperx').name}`, the toss motion, sampling and "
        "predicted-reward scoring.\n"
    )
    if skipped:
        note += f"\nNot run (section budget): {', '.join(skipped)}.\n"
    return "\n".join(lines) + "\n" + note


def run_online(plan: Plan, device: str, clock: Clock, rows: list[dict]) -> str:
    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.dit.train import TrainConfig, train

    cfg = OnlineConfig(designs=plan.online_designs, motions=4, refresh_every=max(1, plan.online_steps // 3))
    source = OnlineTokenSource(cfg, device=device)
    stamps = []
    with tempfile.TemporaryDirectory() as out:
        tcfg = TrainConfig(
            out=out,
            task="both",
            size=plan.online_size,
            steps=plan.online_steps,
            batch_size=plan.online_batch,
            device=device,
            checkpoint_every=10**9,
            resume=False,
            warmup_steps=2,
            online=cfg,
        )
        t0 = time.perf_counter()
        train(tcfg, episodes=source, on_step=lambda step, loss: stamps.append(time.perf_counter()))
        _sync(device)
        seconds = time.perf_counter() - t0
    rate = plan.online_steps / seconds
    share = source.stats["seconds"] / seconds
    _emit(
        rows,
        {
            "section": "online",
            "size": plan.online_size,
            "batch": plan.online_batch,
            "steps": plan.online_steps,
            "steps_per_s": rate,
            "samples_per_s": rate * plan.online_batch,
            "generation_share": share,
            "refreshes": source.stats["refreshes"],
            "world_steps": source.stats["world_steps"],
        },
    )
    return (
        f"`tt train --online` ({plan.online_size}, both tasks, batch {plan.online_batch}, {plan.online_designs} "
        f"designs x 4 motions every {cfg.refresh_every} steps): {rate:.3g} steps/s = {rate * plan.online_batch:.3g} "
        f"samples/s over {plan.online_steps} steps ({source.stats['refreshes']} refreshes, generation "
        f"{100 * share:.0f} % of the wall time, first-step compile included).\n"
    )


RUNNERS = {
    "tests": run_tests,
    "rollout": run_rollout,
    "training": run_training,
    "sampling": run_sampling,
    "online": run_online,
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu")
    p.add_argument("--quick", action="store_true", help="tiny sizes (the test's mode; with --device cpu)")
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    args = p.parse_args(argv)
    device = "cuda:0" if args.device == "cuda" else args.device
    if device.startswith("cuda"):
        import torch
        import warp as wp

        if not (torch.cuda.is_available() and wp.is_cuda_available()):
            p.error(f"--device {args.device}: torch or Warp sees no CUDA device; use --device cpu")
    plan = QUICK if args.quick else FULL
    rows: list[dict] = []
    started = time.perf_counter()
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    body = []
    for name in args.sections:
        t0 = time.perf_counter()
        clock = Clock(plan.budget[name])
        try:
            text = RUNNERS[name](plan, device, clock, rows)
        except Exception as err:  # one broken section must not cost the others
            text = f"failed: `{type(err).__name__}: {err}`\n"
            _emit(rows, {"section": name, "error": f"{type(err).__name__}: {err}"})
        body.append(f"## {name} ({time.perf_counter() - t0:.0f} s of a {plan.budget[name]:.0f} s budget)\n\n{text}")
    total = time.perf_counter() - started
    gpu = ""
    if device.startswith("cuda"):
        import torch

        gpu = f"- GPU: {torch.cuda.get_device_name(device)}, torch CUDA {torch.version.cuda}\n"
    header = (
        f"# GPU benchmark ({'quick, ' if args.quick else ''}device {device})\n\n"
        + machine_header(device)
        + gpu
        + f"- load average at start: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}\n"
        + f"- command: `python benchmarks/gpu.py {' '.join(argv if argv is not None else sys.argv[1:])}`\n"
        + f"- total: {total:.0f} s\n\n"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(header + "\n".join(body) + "\n<!-- rows\n" + json.dumps(rows, indent=1) + "\n-->\n")
    print(f"wrote {args.out} in {total:.0f} s", flush=True)
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
