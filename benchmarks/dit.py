"""DiT throughput on this machine: training steps/s and DDIM sampling time.

Models: the paper's small DiT (256 hidden, 8 layers, 4 heads) and tt's mini one (128
hidden, 4 layers, 4 heads: the size of the shipped ViperX checkpoint), on the RoboToken
layout of the ViperX design space. Sequence lengths come from the tokenizer: the largest token
count of each type over sampled ViperX designs (embodiment types per robot; per-step
types per control step, times the 8-step window).

* Training: ``train()`` on synthetic episodes of that layout (`tt.dit.toy`; values do not
  change the cost), motion-to-robot task, batch 64; the first step is a warm-up and is not
  timed; the last (which writes a checkpoint) is not timed either.
* Sampling: motion-to-robot DDIM (100 steps, eta 0) for 1, 16 and 128 candidates. Every
  step costs the same, so each case times ``measure`` steps after one warm-up step and
  reports ``per step x 100``; the table says how many steps were timed.
* Control (the model as controller, `tt.dit.policies`): one control step is the control
  task's 5 DDIM steps over a batch of worlds; timed for 1, 16 and 128 worlds (network and
  sampler only; building the query and the physics come on top).

Prints one JSON line per measurement (``{"bench": "dit", ...}``) and writes
``benchmarks/results/dit.md``. Usage: ``python benchmarks/dit.py [--sizes small,mini] [--train-steps 3]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from tt.dit.ddim import CosineDDIM
from tt.dit.layout import layout_from_schema
from tt.dit.model import RoboDiT, get_config
from tt.dit.sampling import sample
from tt.dit.tasks import CONTROL, ROBOT
from tt.dit.toy import toy_episodes
from tt.dit.train import TrainConfig, train

RESULTS = Path(__file__).parent / "results" / "dit.md"


def viperx_counts(designs: int = 200, seed: int = 0) -> dict[str, int]:
    """Largest token counts of the ViperX space as the tokenizer produces them."""
    from tt.sim.designs import get_space
    from tt.tokens.tokenize import tokenize_models

    space = get_space("viperx")
    emb = tokenize_models([space.model(d) for d in space.sample(designs, seed)])
    counts = {n: int(np.asarray(emb.tokens.mask[n]).sum(1).max()) for n in emb.tokens.types}
    joints = max(r.counts["dyna_joint"] for r in emb.index)
    actuators = max(r.counts["actuator"] for r in emb.index)
    tracks = max(r.counts["track_link"] for r in emb.index)
    counts.update(
        track_link_obs=tracks, target_pose=tracks, dyna_joint_obs=joints, actuator_obs=actuators, control=actuators
    )
    return {k: v for k, v in counts.items() if v > 0}


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=Path(__file__).parent,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def emit(**fields) -> dict:
    print(json.dumps({"bench": "dit", **fields}), flush=True)
    return fields


def bench_train(episodes, steps: int, size: str) -> dict:
    stamps = []
    with tempfile.TemporaryDirectory() as out:
        config = TrainConfig(
            out=out,
            task="robot",
            size=size,
            steps=steps,
            batch_size=64,
            device="cpu",
            checkpoint_every=10**9,
            resume=False,
        )
        result = train(config, episodes=episodes, on_step=lambda s, loss: stamps.append(time.perf_counter()))
    # stamps[i] is taken after step i+1; steps 2 .. steps-1 are timed (no warm-up, no checkpoint).
    timed = np.diff(stamps[:-1])
    if len(timed) == 0:
        raise ValueError("--train-steps must be >= 3 (one warm-up step, one timed step, one checkpointing step)")
    return emit(
        metric="train_step",
        size=size,
        batch=64,
        task="robot",
        timed_steps=int(len(timed)),
        seconds_per_step=float(timed.mean()),
        steps_per_s=float(1.0 / timed.mean()),
        parameters=result.parameters,
    )


def bench_sample(model, normalizer, episodes, candidates: int, measure: int, size: str) -> dict:
    tokens = normalizer.normalize(episodes.sample(candidates, 8, "random", torch.Generator().manual_seed(0)))
    sched = CosineDDIM(100)
    sample(model, tokens, ROBOT, scheduler=sched, num_steps=1)  # warm-up
    t0 = time.perf_counter()
    sample(model, tokens, ROBOT, scheduler=sched, num_steps=measure, generator=torch.Generator().manual_seed(1))
    per_step = (time.perf_counter() - t0) / measure
    return emit(
        metric="sample",
        size=size,
        candidates=candidates,
        timed_steps=measure,
        seconds_per_step=per_step,
        seconds_per_100_steps=100 * per_step,
    )


def bench_control(model, normalizer, episodes, worlds: int, size: str) -> dict:
    """One control step: the control task's 5 DDIM steps over `worlds` windows (one warm-up call first)."""
    tokens = normalizer.normalize(episodes.sample(worlds, 8, "consecutive", torch.Generator().manual_seed(0)))
    sched = CosineDDIM(CONTROL.diffusion_steps)
    sample(model, tokens, CONTROL, scheduler=sched, num_steps=1)  # warm-up
    t0 = time.perf_counter()
    sample(model, tokens, CONTROL, scheduler=sched, generator=torch.Generator().manual_seed(1))
    seconds = time.perf_counter() - t0
    return emit(metric="control_step", size=size, worlds=worlds, ddim_steps=CONTROL.diffusion_steps, seconds=seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train-steps", type=int, default=3, help="training steps to run (first and last untimed)")
    parser.add_argument("--sizes", type=str, default="small,mini", help="model sizes to measure, comma-separated")
    parser.add_argument(
        "--sample-steps", type=str, default="1:10,16:3,128:1", help="candidates:timed-steps pairs for sampling"
    )
    parser.add_argument("--control-worlds", type=str, default="1,16,128", help="batches for the control-step timing")
    parser.add_argument("--out", type=str, default=str(RESULTS), help="results markdown file")
    parser.add_argument(
        "--threads",
        type=int,
        default=0,
        help="torch CPU threads (0: torch's default); on a shared machine 1 avoids "
        "OpenMP threads waiting on each other",
    )
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    sizes = [x for x in args.sizes.split(",") if x]
    load_before = os.getloadavg()
    started = time.perf_counter()
    counts = viperx_counts()
    layout = layout_from_schema(counts, steps=8)
    episodes = toy_episodes(episodes=64, steps=32, seed=0, schema_counts=counts)
    normalizer = episodes.fit_normalizer()
    emit(metric="layout", seq_len=layout.seq_len, **{f"len_{s.name}": s.length for s in layout.specs})

    results = {}
    for size in sizes:
        rows_train = bench_train(episodes, args.train_steps, size)
        torch.manual_seed(0)
        model = RoboDiT(episodes.layout(8), get_config(size)).eval()
        rows_sample = []
        for pair in args.sample_steps.split(","):
            b, k = (int(x) for x in pair.split(":"))
            rows_sample.append(bench_sample(model, normalizer, episodes, b, k, size))
        rows_control = [
            bench_control(model, normalizer, episodes, int(w), size) for w in args.control_worlds.split(",") if w
        ]
        results[size] = (rows_train, rows_sample, rows_control)
    load_after = os.getloadavg()
    total = time.perf_counter() - started

    def describe(size: str) -> str:
        c = get_config(size)
        return (
            f"{size} ({c.hidden} hidden, {c.depth} layers, {c.heads} heads; "
            f"{results[size][0]['parameters'] / 1e6:.2f} M parameters)"
        )

    table = []
    for size, (rows_train, rows_sample, rows_control) in results.items():
        table += [
            f"| {size} | training (motion-to-robot, AdamW + EMA) | 64 | {rows_train['timed_steps']} | "
            f"{rows_train['seconds_per_step']:.2f} | {rows_train['steps_per_s']:.3f} steps/s |",
            *[
                f"| {size} | sampling, 100 DDIM steps | {r['candidates']} | {r['timed_steps']} | "
                f"{r['seconds_per_step']:.3f} "
                f"| {r['seconds_per_100_steps']:.1f} s |"
                for r in rows_sample
            ],
            *[
                f"| {size} | control step (5 DDIM steps, control task) | {r['worlds']} | 5 | {r['seconds'] / 5:.3f} "
                f"| {r['seconds']:.2f} s |"
                for r in rows_control
            ],
        ]
    lines = [
        "# DiT throughput (CPU)",
        "",
        f"- date: {datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- machine: {cpu_name()}, {os.cpu_count()} logical CPUs, torch threads {torch.get_num_threads()}",
        f"- load average (1 min) before / after: {load_before[0]:.1f} / {load_after[0]:.1f} "
        "(other jobs on the machine slow every number below)",
        f"- versions: python {platform.python_version()}, torch {torch.__version__}, numpy {np.__version__}, "
        f"tt {git_commit()}",
        f"- models: {'; '.join(describe(s) for s in results)}; float32, eager",
        f"- benchmark wall time: {total:.0f} s",
        "",
        "Sequence (ViperX, largest designs as tokenized by `tt.tokens`, 8-step window):",
        "",
        "| type | tokens |",
        "|---|---:|",
        *[
            f"| {s.name} | {s.length}" + (f" ({s.per_step} per step)" if s.per_step else "") + " |"
            for s in layout.specs
        ],
        f"| **total** | **{layout.seq_len}** |",
        "",
        "| size | measurement | batch | timed steps | s / step | result |",
        "|---|---|---:|---:|---:|---:|",
        *table,
        "",
        "Sampling time for 100 steps is the timed per-step cost times 100 (all steps cost the same). A control",
        "step is the model's share of one step of the model-as-controller (`tt.dit.policies`): 5 DDIM steps of",
        "the control task over a batch of worlds.",
        "",
    ]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    emit(metric="written", path=str(out))


if __name__ == "__main__":
    main()
