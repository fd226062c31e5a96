"""The quadruped on the ``mjbatch`` backend against the oracle: closed-loop world-steps/s at
1 and 2 threads, in one process, with what one world-step costs.

D random quadruped designs (seed 0, any mix of the 128 structures) x one validation
motion (``--motion``, placed by the space's ``motion_offset``; its first ``--steps``
control steps, 0 for all). A world-step is one physics step (0.002 s) of one world, the
50 Hz whole-body controller included, counted over the motion's length (as `tt rollout`
counts them). Every timed call includes its setup: compiling the designs' MuJoCo models in
this process (the backend's `resolve`; `tt rollout` builds 512 or more in 2 worker processes,
which on 2 cores about break even for the quadruped: 2.8-3.0 s against 2.9-3.2 s in-process
for 1,024 designs, `DesignSpace.models`, Intel Xeon, 2026-12-08) and
the rollout's own (batches, controller arrays, start postures); Warp's whole-body kernels
are loaded by a 2-step warm-up first.

* oracle: MuJoCo C + mink, one world after another (`tt.sim.validate.oracle_rollout`),
  on the first ``--oracle-designs`` designs: its rate does not depend on the batch.
* mjbatch: `tt.sim.mjbatch_backend` on all D designs at each ``--threads`` count.
The calls alternate over ``--repeats`` rounds and the best of each is reported, per wall
second and per CPU second of the process (the latter least disturbed by other jobs).
Then: the cost of one ``mj_step``, one forward to the velocity stage (what mjbatch runs after a
control step's ``mj_step``s: ``mj_fwdPosition`` and ``mj_fwdVelocity``) and one whole-body
kernel step per world (why a core tops out where it does); the agreement of the mjbatch episodes with the
oracle's on the common designs (per-episode mean position error, survived / fell); that
every thread count gave the same Episode; and, with ``--cli``, `tt rollout --space
quadruped --backend mjbatch` on the same designs and the whole motion in a subprocess
(model building in worker processes, scoring included).

``--part agreement`` measures the issue's agreement instead (``--agreement-designs`` random
designs, seed 7, x ``--agreement-motions`` validation motions, on the oracle and on
mjbatch), ``--part cli`` the `tt rollout` run alone; ``--from-raw SPEED.json AGREEMENT.json
CLI.json`` writes one report from the parts.

Usage:
    python benchmarks/quadruped_batched.py [--designs 1024] [--oracle-designs 48] [--motion toss:100]
        [--steps 50] [--threads 1 2] [--repeats 2] [--cli] [--raw SPEED.json]
    python benchmarks/quadruped_batched.py --part agreement [--agreement-designs 100]
        [--agreement-motions 5] --raw AGREEMENT.json
    python benchmarks/quadruped_batched.py --from-raw SPEED.json AGREEMENT.json
        [--out benchmarks/results/quadruped_batched.md]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

try:
    from machine import load_line, machine_header, write_report
except ImportError:  # run as a module from the repository root
    from benchmarks.machine import load_line, machine_header, write_report

SPACE = "quadruped"


def _motion(name: str, steps: int):
    from tt.sim.motions import for_space, resolve_motion
    from tt.sim.motions.base import Motion

    motion = for_space([resolve_motion(name)], SPACE)[0]
    if steps <= 0 or steps >= motion.steps:
        return motion
    return Motion(f"{motion.name}[:{steps}]", motion.pos[:steps], motion.quat[:steps], motion.dt)


def _timed(fn) -> tuple[object, float, float]:
    """(result, wall s, process CPU s) of fn()."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def _costs(designs, samples: int = 64, steps: int = 200, wbc_worlds: int = 256) -> dict:
    """Mean cost [us] of one mj_step and one forward to the velocity stage (mj_fwdPosition,
    mj_fwdVelocity: what mjbatch runs after a control step's mj_steps) per world (standing, home keyframe,
    the first `samples` designs) and of one whole-body kernel step per world (a launch over
    the first `wbc_worlds` designs: fewer would measure Python's launch overhead)."""
    import mujoco
    import warp as wp

    from tt.kernels.wbc import make_wbc_data, wbc_step
    from tt.sim.designs import get_space
    from tt.sim.wbc import HOME_KEY, WBCConfig
    from tt.sim.wbc_model import build_wbc_model

    sp = get_space(SPACE)
    models = [sp.model(d) for d in designs[: max(samples, wbc_worlds)]]
    step_s, fwd_s = [], []
    for m in models[:samples]:
        d = mujoco.MjData(m)
        mujoco.mj_resetDataKeyframe(m, d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, HOME_KEY))
        for _ in range(20):
            mujoco.mj_step(m, d)
        t = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(m, d)
        step_s.append((time.perf_counter() - t) / steps)
        t = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_fwdPosition(m, d)
            mujoco.mj_fwdVelocity(m, d)
        fwd_s.append((time.perf_counter() - t) / steps)
    W = len(models)
    wbc = build_wbc_model(models, WBCConfig(), device="cpu")
    data = make_wbc_data(wbc, W, device="cpu")
    q = np.zeros((W, wbc.nq))
    for i, m in enumerate(models):
        q[i, : m.nq] = m.key_qpos[0]
    qw = wp.array(q, dtype=wp.float64, device="cpu")
    tp = wp.array(np.tile([0.35, 0.0, 0.7], (W, 1, 1)), dtype=wp.vec3d, device="cpu")
    tq = wp.array(np.tile([1.0, 0.0, 0.0, 0.0], (W, 1, 1)), dtype=wp.vec4d, device="cpu")
    out = wp.zeros((W, wbc.nq), dtype=wp.float64, device="cpu")
    wbc_step(wbc, qw, tp, tq, out, data=data, device="cpu")
    reps = 20
    t = time.perf_counter()
    for _ in range(reps):
        wbc_step(wbc, qw, tp, tq, out, data=data, device="cpu")
    wbc_s = (time.perf_counter() - t) / reps / W
    return {
        "mj_step_us": 1e6 * float(np.mean(step_s)),
        "mj_step_us_range": [1e6 * float(np.min(step_s)), 1e6 * float(np.max(step_s))],
        "forward_vel_us": 1e6 * float(np.mean(fwd_s)),
        "wbc_step_us": 1e6 * wbc_s,
        "designs": min(samples, W),
        "wbc_worlds": W,
    }


def _physics_scaling(seconds: float = 12.0, sims: int = 64) -> dict:
    """What two cores give MuJoCo C alone, with no Python in the loop: `sims` standing
    nominal quadrupeds in a `mujoco.batch.Batch` stepped as mjbatch steps them (10 steps, then the
    forward to the velocity stage, per call)
    for `seconds` on one thread, then two such batches for `seconds` on two threads at once;
    world-steps/s of each."""
    import threading

    import mujoco
    from mujoco.batch import Batch

    from tt.sim.designs import get_space
    from tt.sim.wbc import HOME_KEY

    sp = get_space(SPACE)
    model = sp.model(sp.nominal())
    key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, HOME_KEY)
    vel = mujoco.mjtStage.mjSTAGE_VEL.value
    batches = []
    for _ in range(2):
        b = Batch(model, nsim=sims, nthread=1)
        b.reset(keyframe=np.full(sims, key, np.int32))
        batches.append(b)
    done: dict[int, float] = {}

    def work(i: int) -> None:
        start, n = time.perf_counter(), 0
        while time.perf_counter() - start < seconds:
            batches[i].step(nstep=10, stage=vel)
            n += 1
        done[i] = sims * 10 * n / (time.perf_counter() - start)

    work(0)
    solo = done.pop(0)
    threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    pair = done[0] + done[1]
    return {"one_thread": solo, "two_threads": pair, "speedup": pair / solo, "seconds": seconds}


def _cli(designs: int, motion: str, threads: int | None) -> dict:
    """`tt rollout --space quadruped --backend mjbatch` in a subprocess: its own rate line."""
    cmd = ["tt", "rollout", "--space", SPACE, "--backend", "mjbatch", "--n", str(designs), "--motion", motion]
    if threads:
        cmd += ["--threads", str(threads)]
    wall = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    wall = time.perf_counter() - wall
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{res.stderr[-3000:]}")
    line = next(x for x in res.stdout.splitlines()[::-1] if "world-steps/s" in x)
    rate = float(re.search(r"([\d,]+) world-steps/s", line).group(1).replace(",", ""))
    return {"command": " ".join(cmd), "line": line.strip(), "world_steps_per_s": rate, "process_wall_s": wall}


def run(args) -> dict:
    import torch

    from tt.baselines.evaluate import score_episode
    from tt.sim.backends import get_backend
    from tt.sim.designs import get_space
    from tt.sim.mjbatch_backend import mjbatch_rollout
    from tt.sim.validate import oracle_rollout
    from tt.sim.wbc import WBCConfig

    sp = get_space(SPACE)
    designs = sp.sample(args.designs, 0)
    oracle_designs = designs[: args.oracle_designs]
    motion = _motion(args.motion, args.steps)
    substeps = WBCConfig().substeps(sp.model(designs[0]))
    world_steps = {
        "oracle": substeps * len(oracle_designs) * motion.steps,
        "mjbatch": substeps * len(designs) * motion.steps,
    }
    backend = get_backend("mjbatch")

    def oracle():
        return oracle_rollout(get_backend("mujoco").resolve(oracle_designs), [motion])

    compile_s: dict[int, float] = {}

    def batched(threads):
        def call():
            start = time.perf_counter()
            robots = backend.resolve(designs)
            compile_s[threads] = time.perf_counter() - start
            return mjbatch_rollout(robots, [motion], threads=threads)

        return call

    # Warm-up: Warp's whole-body kernels (cached on disk) and the first calls of each path.
    short = _motion(args.motion, 2)
    mjbatch_rollout(backend.resolve(designs[:4]), [short], threads=1)
    oracle_rollout(designs[:1], [short])

    runs: dict[str, list] = {"oracle": []}
    runs.update({f"mjbatch/{t}": [] for t in args.threads})
    episodes = {}
    loads = [load_line()]
    for r in range(args.repeats):
        for name in runs:
            fn = oracle if name == "oracle" else batched(int(name.split("/")[1]))
            ep, wall, cpu = _timed(fn)
            if r == 0:
                episodes[name] = ep
            ws = world_steps[name.split("/")[0]]
            runs[name].append({"wall_s": wall, "cpu_s": cpu, "world_steps_per_s": ws / wall, "per_cpu_s": ws / cpu})
            if name != "oracle":  # the models' compile (serial: MJCF in Python, MuJoCo's compiler) apart
                t = int(name.split("/")[1])
                runs[name][-1].update(compile_s=compile_s[t], rollout_per_s=ws / (wall - compile_s[t]))
            print(json.dumps({"run": name, "round": r, **runs[name][-1], "load": load_line()}), flush=True)
    loads.append(load_line())
    # Setup alone: compile, batches, controller arrays, start postures and one control step.
    one = _motion(args.motion, 1)
    setup = {
        str(t): _timed(lambda: mjbatch_rollout(backend.resolve(designs), [one], threads=t))[1] for t in args.threads
    }
    print(json.dumps({"setup_s": setup}), flush=True)

    # Every thread count: the same Episode.
    names = [n for n in episodes if n != "oracle"]
    first = episodes[names[0]]
    identical = all(
        torch.equal(getattr(episodes[n], f), getattr(first, f))
        for n in names[1:]
        for f in ("qpos", "qvel", "ctrl", "act_force", "ee_pos", "ee_quat", "alive", "fallen")
    )
    # Agreement with the oracle on the common designs.
    k = len(oracle_designs)
    ref = episodes["oracle"]
    mine = first
    sub = {f: getattr(mine, f)[:k] for f in ("ee_pos", "alive", "fallen")}
    _, m_mine = score_episode(_slice(mine, k), oracle_designs, [motion], "tracking")
    _, m_ref = score_episode(ref, oracle_designs, [motion], "tracking")
    gap = np.abs(m_mine["pos_err"] - m_ref["pos_err"]).ravel()
    same = (
        (sub["alive"].sum(1) == ref.alive.sum(1)).numpy()
        & (sub["fallen"].any(1) == ref.fallen.any(1)).numpy()
        & (m_mine["survival"] == m_ref["survival"]).ravel()
    )
    agreement = {
        "episodes": k,
        "pos_err_gap_cm_max": float(gap.max()),
        "within_0.3cm": float(np.mean(gap <= 0.3)),
        "same_outcome": float(np.mean(same)),
        "ee_pos_max_diff_m": float((sub["ee_pos"] - ref.ee_pos).abs().max()),
        "oracle_pos_err_cm": float(m_ref["pos_err"].mean()),
        "survival": float(np.mean(m_ref["survival"])),
        "fell": float(ref.fallen.any(1).float().mean()),
    }
    costs = _costs(designs)
    costs["physics_scaling"] = _physics_scaling()
    print(json.dumps({"costs": costs, "agreement": agreement, "identical_across_threads": identical}), flush=True)
    cli = _cli(args.designs, args.motion, max(args.threads)) if args.cli else None
    if cli:
        print(json.dumps({"cli": cli}), flush=True)
    args_json = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    return {
        "args": args_json, "motion": motion.name, "motion_steps": motion.steps, "substeps": substeps,
        "world_steps": world_steps, "runs": runs, "loads": loads, "identical_across_threads": identical,
        "agreement": agreement, "costs": costs, "cli": cli, "header": machine_header("cpu"), "setup_s": setup,
    }  # fmt: skip


def run_agreement(args) -> dict:
    """The issue's agreement measure: --agreement-designs random designs (seed 7) x
    --agreement-motions validation motions spread over the 30, on the oracle and on mjbatch."""
    import torch

    from tt.baselines.evaluate import score_episode
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, motion_set
    from tt.sim.rollout import rollout
    from tt.sim.validate import oracle_rollout

    sp = get_space(SPACE)
    designs = sp.sample(args.agreement_designs, 7)
    val = for_space(motion_set("val", arms=1), SPACE)
    picks = np.linspace(0, len(val) - 1, args.agreement_motions).round().astype(int)
    motions = [val[i] for i in picks]
    loads = [load_line()]
    ref, oracle_wall, _ = _timed(lambda: oracle_rollout(designs, motions))
    ep, mine_wall, _ = _timed(lambda: rollout(designs, motions, backend="mjbatch"))
    loads.append(load_line())
    _, a = score_episode(ep, designs, motions, "tracking")
    _, b = score_episode(ref, designs, motions, "tracking")
    gap = np.abs(a["pos_err"] - b["pos_err"]).ravel()
    same = (
        (ep.alive.sum(1) == ref.alive.sum(1)).numpy()
        & (ep.fallen.any(1) == ref.fallen.any(1)).numpy()
        & (a["survival"] == b["survival"]).ravel()
    )
    steps = sum(m.steps for m in motions) * len(designs)
    return {
        "designs": len(designs), "motions": [m.name for m in motions], "episodes": int(gap.size),
        "within_0.3cm": float(np.mean(gap <= 0.3)), "same_outcome": float(np.mean(same)),
        "gap_cm": {str(q): float(np.percentile(gap, q)) for q in (50, 95, 99, 100)},
        "identical_ee": float(torch.mean((ep.ee_pos == ref.ee_pos).all(-1).all(-1).all(-1).float())),
        "ee_pos_max_diff_m": float((ep.ee_pos - ref.ee_pos).abs().max()),
        "oracle_pos_err_cm": float(np.nanmean(b["pos_err"])), "mjbatch_pos_err_cm": float(np.nanmean(a["pos_err"])),
        "oracle_survival": float(np.mean(b["survival"])), "mjbatch_survival": float(np.mean(a["survival"])),
        "oracle_fell": float(ref.fallen.any(1).float().mean()), "mjbatch_fell": float(ep.fallen.any(1).float().mean()),
        "oracle_wall_s": oracle_wall, "mjbatch_wall_s": mine_wall, "control_steps": steps, "loads": loads,
    }  # fmt: skip


def _slice(ep, k: int):
    """The first k worlds of an Episode (one motion: the first k designs)."""
    from dataclasses import fields, replace

    return replace(
        ep, **{f.name: getattr(ep, f.name)[:k] for f in fields(ep) if f.name != "dt"}
    )  # fmt: skip


def _fmt(x: float) -> str:
    return f"{x / 1e3:.1f} k" if x >= 1e3 else f"{x:.0f}"


def _round_row(runs: dict, k: int, thread_counts: list[int]) -> str:
    """Round k's row: the oracle's and each thread count's world-steps/s and the speed-up, then
    the same without the models' compile where the round timed it."""
    out = []
    for key in ("world_steps_per_s", "rollout_per_s"):
        rate = {t: runs[f"mjbatch/{t}"][k].get(key) for t in thread_counts}
        if None in rate.values():
            out.append(" | ".join("-" for _ in thread_counts) + " | -")
            continue
        speedup = f"{rate[max(thread_counts)] / rate[min(thread_counts)]:.2f}x" if len(thread_counts) > 1 else "-"
        out.append(" | ".join(_fmt(rate[t]) for t in thread_counts) + f" | {speedup}")
    return f"| {k + 1} | {_fmt(runs['oracle'][k]['world_steps_per_s'])} | {out[0]} | {out[1]} |"


def physics_ceiling(raw: dict) -> tuple[float, float]:
    """(world-steps/s one core tops out at with the oracle's physics alone, that rate over the
    oracle's best rate times the most threads timed): the substeps' ``mj_step``s and one
    forward to the velocity stage per control step at their measured costs, a free controller,
    perfect scaling."""
    c, runs = raw["costs"], raw["runs"]
    physics_core = 1e6 / (c["mj_step_us"] + c["forward_vel_us"] / raw["substeps"])
    oracle = max(r["world_steps_per_s"] for r in runs["oracle"])
    threads = max(int(n.split("/")[1]) for n in runs if n != "oracle")
    return physics_core, threads * physics_core / oracle


def report(raw: dict, command: str) -> list[str]:
    a, runs = raw["args"], raw["runs"]
    best = {name: max(rs, key=lambda r: r["world_steps_per_s"]) for name, rs in runs.items()}
    best_cpu = {name: max(r["per_cpu_s"] for r in rs) for name, rs in runs.items()}
    oracle = best["oracle"]["world_steps_per_s"]
    oracle_cpu = best_cpu["oracle"]
    thread_counts = [int(n.split("/")[1]) for n in runs if n != "oracle"]
    lines = [
        "# The quadruped on the mjbatch backend: world-steps/s against the oracle",
        "",
        raw["header"].rstrip("\n"),
        *[f"- command: `{c}`" for c in raw.get("commands", [command])],
        *(
            [
                "- the merged measurements: benchmarks/results/quadruped_batched.json; `python "
                "benchmarks/quadruped_batched.py --from-raw benchmarks/results/quadruped_batched.json` rewrites "
                "this page"
            ]
            if len(raw.get("commands", [])) > 1
            else []
        ),
        *[
            f"- load average (1, 5, 15 min) {lo[0]} at the start, {lo[1]} at the end of the timed runs"
            + (f" of invocation {i + 1}" if len(raw.get("load_runs", [])) > 1 else "")
            + f", on {os.cpu_count()} cores"
            for i, lo in enumerate(raw.get("load_runs", [raw["loads"]]))
        ],
        "",
        f"{a['designs']} random quadruped designs (seed 0; any mix of the 128 structures) x {raw['motion']} "
        f"({raw['motion_steps']} control steps at 50 Hz, {raw['substeps']} physics steps of 0.002 s each), in one "
        f"process; the oracle on the first {a['oracle_designs']} of them (one world after another: its rate does "
        "not depend on the batch). A world-step is one physics step of one world, the 50 Hz whole-body controller "
        "included; every call includes its setup (compiling the designs' MuJoCo models in this process, the "
        "rollout's batches, controller arrays and start postures). Best of "
        f"{len(runs['oracle'])} alternating rounds"
        + (f" over {len(raw['commands'])} invocations" if len(raw.get("commands", [])) > 1 else "")
        + "; every round:",
        "",
        "| round | oracle (world-steps/s) | "
        + " | ".join(f"mjbatch, {t} thread{'s' if t > 1 else ''}" for t in thread_counts)
        + " | speed-up | "
        + " | ".join(f"without the compile, {t} thread{'s' if t > 1 else ''}" for t in thread_counts)
        + " | speed-up |",
        "|---|---|" + "---|" * (2 * len(thread_counts) + 2),
        *[_round_row(runs, k, thread_counts) for k in range(len(runs["oracle"]))],
        "",
        "The best of each:",
        "",
        "| path | designs | threads | wall (s) | world-steps/s | control steps/s | x oracle | world-steps per CPU s | "
        "CPU s / wall s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in best.items():
        is_oracle = name == "oracle"
        n = a["oracle_designs"] if is_oracle else a["designs"]
        threads = "1" if is_oracle else name.split("/")[1]
        label = "oracle (MuJoCo C + mink)" if is_oracle else "mjbatch (MuJoCo C batch + WBC kernel)"
        rate = r["world_steps_per_s"]
        lines.append(
            f"| {label} | {n} | {threads} | {r['wall_s']:.1f} | {_fmt(rate)} | {_fmt(rate / raw['substeps'])} | "
            f"{rate / oracle:.1f}x | {_fmt(best_cpu[name])} | {r['cpu_s'] / r['wall_s']:.2f} |"
        )
    if len(thread_counts) > 1:
        lo, hi = min(thread_counts), max(thread_counts)
        speedup = best[f"mjbatch/{hi}"]["world_steps_per_s"] / best[f"mjbatch/{lo}"]["world_steps_per_s"]
        per_round = [
            r_hi["world_steps_per_s"] / r_lo["world_steps_per_s"]
            for r_lo, r_hi in zip(runs[f"mjbatch/{lo}"], runs[f"mjbatch/{hi}"])
        ]
        rounds_met = sum(x >= 1.7 for x in per_round)
        no_compile = [
            r_hi["rollout_per_s"] / r_lo["rollout_per_s"]
            for r_lo, r_hi in zip(runs[f"mjbatch/{lo}"], runs[f"mjbatch/{hi}"])
            if "rollout_per_s" in r_lo and "rollout_per_s" in r_hi
        ]
        nc = f"; {min(no_compile):.2f}-{max(no_compile):.2f}x without the models' compile" if no_compile else ""
        lines += [
            "",
            f"Speed-up {lo} -> {hi} threads (wall): {speedup:.2f}x between the bests, "
            f"{min(per_round):.2f}-{max(per_round):.2f}x within a round.",
        ]
    if raw.get("setup_s"):
        parts = ", ".join(f"{v:.1f} s at {k} thread{'s' if k != '1' else ''}" for k, v in raw["setup_s"].items())
        lines += [
            "",
            f"Setup alone (the same call on a 1-step motion: compiling the {a['designs']} models, "
            f"the batches, the controller arrays, the start postures and one control step): {parts}.",
        ]
    c = raw["costs"]
    per_core = 1e6 / (c["mj_step_us"] + (c["forward_vel_us"] + c["wbc_step_us"]) / raw["substeps"])
    if len(thread_counts) > 1:
        top = best[f"mjbatch/{max(thread_counts)}"]["world_steps_per_s"]
        physics_core, cap = physics_ceiling(raw)
        two = [r["world_steps_per_s"] for r in runs[f"mjbatch/{max(thread_counts)}"]]
        over = [x for x in two if x >= 50_000]
        ratios = [
            r["world_steps_per_s"] / o["world_steps_per_s"]
            for r, o in zip(runs[f"mjbatch/{max(thread_counts)}"], runs["oracle"])
        ]
        ceiling = max(thread_counts) * physics_core

        def met(ok: bool) -> str:
            return "met" if ok else "not met"

        lines += [
            "",
            "## Against the issue's targets",
            "",
            "| target | measured | |",
            "|---|---|---|",
            f"| >= 10x the oracle's world-steps/s | {top / oracle:.1f}x between the bests, "
            f"{min(ratios):.1f}-{max(ratios):.1f}x within a round | {met(top >= 10 * oracle)} |",
            f"| >= 50,000 world-steps/s | {top:,.0f} (best round) | "
            + (met(top >= 50_000) if len(over) in (0, len(two)) else f"met in {len(over)} of {len(two)} rounds")
            + " |",
            f"| 1 -> 2 thread speed-up >= 1.7x | {min(per_round):.2f}-{max(per_round):.2f}x per round{nc} | "
            f"{'met' if rounds_met == len(per_round) else f'met in {rounds_met} of {len(per_round)} rounds'} |",
            "",
            f"Why not 10x: the physics is the oracle's own, and it alone (10 `mj_step`s and one forward to the "
            f"velocity stage per control step, below) caps a core near {_fmt(physics_core)} world-steps/s, "
            f"so {max(thread_counts)} cores cap at {_fmt(ceiling)}, "
            f"{cap:.1f}x this oracle, even with a free controller and perfect scaling. The oracle's "
            f"{_fmt(oracle)} world-steps/s is its rate in this run (loads above); benchmarks/results/quadruped.md "
            f"measured 3.1-6.0 k at load averages of 5-8, against which this would read {top / 6.0e3:.1f}-"
            f"{top / 3.1e3:.1f}x. More "
            "than the ceiling needs cheaper physics than the oracle's, and its solver has little to give: the "
            "warm-started Newton solver converges in about one iteration per step, and no other solver option "
            "that keeps the episodes costs less, and the forward after each control step stops at the velocity "
            "stage already (benchmarks/results/quadruped_solver.md); another integrator, "
            "timestep or contact model would no longer give the oracle's episodes.",
        ]
    lines += [
        "",
        "## What one world-step costs",
        "",
        f"Measured on {c['designs']} of the designs ({c.get('wbc_worlds', c['designs'])} in one launch for the "
        f"kernel), standing: one `mj_step` {c['mj_step_us']:.1f} us (per design "
        f"{c['mj_step_us_range'][0]:.1f}-{c['mj_step_us_range'][1]:.1f} us), one forward to the velocity stage "
        f"{c['forward_vel_us']:.1f} us, one whole-body kernel step {c['wbc_step_us']:.1f} us per world. A control "
        f"step is {raw['substeps']} `mj_step`s, one such forward and one controller step, so one core tops out near "
        f"{_fmt(per_core)} world-steps/s; the oracle's mink controller costs far more than its physics "
        f"({_fmt(oracle_cpu)} world-steps per CPU second).",
    ]
    scalings = c.get("physics_scalings") or ([c["physics_scaling"]] if c.get("physics_scaling") else [])
    if scalings:
        ps = scalings[0]
        each = "; ".join(
            f"{_fmt(x['one_thread'])} on one thread, {_fmt(x['two_threads'])} on two, {x['speedup']:.2f}x"
            for x in scalings
        )
        lines += [
            "",
            f"What two cores give MuJoCo C alone (no Python in the loop: 64 standing nominal quadrupeds per "
            f"`mujoco.batch.Batch`, {ps['seconds']:.0f} s on one thread, then two batches for as long on two threads; "
            f"world-steps/s, one measurement per invocation that made it): {each}. This virtual machine's second "
            "core adds less than a first one when both run for tens of seconds, and varies with what else the host "
            "runs, which bounds what any 2-thread path here can show.",
        ]
    lines += ["", "## Agreement and determinism", ""]
    g = raw["agreement"]
    lines += [
        f"On the {g['episodes']} common episodes: per-episode mean position error within 0.3 cm of the oracle's in "
        f"{100 * g['within_0.3cm']:.0f} % (largest gap {g['pos_err_gap_cm_max']:.2g} cm), the same survived / fell "
        f"outcome in {100 * g['same_outcome']:.0f} %, largest end-effector difference {g['ee_pos_max_diff_m']:.2g} m "
        f"(oracle: {g['oracle_pos_err_cm']:.2f} cm mean position error, {100 * g['survival']:.0f} % survived, "
        f"{100 * g['fell']:.0f} % fell). The thread counts gave the same Episode bit for bit: "
        f"{'yes' if raw['identical_across_threads'] else 'NO'}.",
    ]
    lines += [
        "",
        "## The mechanism, and why",
        "",
        "Measured before choosing (this machine, 2026-12-06): `mujoco.mj_step` and `mujoco.batch.Batch.step` "
        "release the GIL (a pure-Python counter thread kept running while either stepped), so threads can step "
        "MuJoCo C in parallel. A plain thread pool over one `MjData` per world would make 11 Python calls per "
        "world and control step (about 1.6 us each, holding the GIL) and copy every record world by world. "
        "`mujoco.batch.Batch` (in the 3.17 wheel) steps any number of simulations per call in C++, each one row "
        "of integration state (warm start included), and copies the derived fields the records need (site frames, "
        "actuator forces and velocities) into (n, ...) arrays; with `set_models` each simulation runs its own "
        "design's model, and models of different structures share a batch when their sizes agree: 1,024 random "
        "designs fall into 10 layouts. A batch of 12 structures stepped 10 steps plus `mj_forward` gave the "
        "loop's qpos, site poses and actuator forces bit for bit. `mujoco.rollout` also takes one model per "
        "world (of one size signature) but returns states only: no site poses or actuator forces (each would need "
        "an `mj_forward` per world in Python) and no warm start carried between calls. MuJoCo-Warp runs random "
        "designs at 0.03x the oracle (benchmarks/results/quadruped.md): every structure is a batch of its own.",
        "",
        "So: `tt.sim.mjbatch_backend` cuts the worlds into one shard per thread; each shard runs its whole "
        "episode on its own thread, with one `Batch` per layout (stepping on that thread) and tt's float64 "
        "whole-body kernel (`tt.kernels.wbc`, one launch per control step for all its worlds, any mix of "
        "structures). Its CPU launch now forms the normal equations one row per thread, skipping zero Jacobian "
        "entries: 38.8 -> 9.6 us per world for that kernel, the same numbers bit for bit. With the oracle's mink "
        "controller in place of the kernel (`controller='mink'`) the episodes equal the oracle's bit for bit "
        "(tests/test_mjbatch.py).",
    ]
    ag = raw.get("agreement_run")
    if ag:
        lines += [
            "",
            f"## Agreement: {ag['designs']} random designs x {len(ag['motions'])} validation motions",
            "",
            f"`{ag['command']}`; designs seed 7, motions {', '.join(ag['motions'])} ({ag['episodes']} episodes, "
            f"{ag['control_steps']:,} control steps); load average {ag['loads'][0]} at the start, {ag['loads'][1]} "
            "at the end. Both paths run every episode; mjbatch with its default controller (the kernel).",
            "",
            "| measure | mjbatch vs oracle | the issue's bar |",
            "|---|---|---|",
            f"| per-episode mean position error within 0.3 cm | {100 * ag['within_0.3cm']:.1f} % | >= 95 % |",
            f"| same survived / fell outcome | {100 * ag['same_outcome']:.1f} % | >= 97 % |",
            "",
            f"Gap in per-episode mean position error: median {ag['gap_cm']['50']:.2g}, 95th percentile "
            f"{ag['gap_cm']['95']:.2g}, largest {ag['gap_cm']['100']:.2g} cm; end-effector positions identical in "
            f"{100 * ag['identical_ee']:.0f} % of the episodes (float32 records), largest difference "
            f"{ag['ee_pos_max_diff_m']:.2g} m. Oracle: {ag['oracle_pos_err_cm']:.3f} cm mean position error, "
            f"{100 * ag['oracle_survival']:.1f} % survived, {100 * ag['oracle_fell']:.1f} % fell; mjbatch: "
            f"{ag['mjbatch_pos_err_cm']:.3f} cm, {100 * ag['mjbatch_survival']:.1f} %, "
            f"{100 * ag['mjbatch_fell']:.1f} %. Wall: oracle {ag['oracle_wall_s']:.0f} s, mjbatch "
            f"{ag['mjbatch_wall_s']:.0f} s (every core, model building included).",
        ]
    if raw.get("cli"):
        cl = raw["cli"]
        lines += [
            "",
            "## Through the CLI",
            "",
            f"`{cl['command']}` (the whole motion; model building in worker processes, scoring included): "
            f"{_fmt(cl['world_steps_per_s'])} world-steps/s, {cl['process_wall_s']:.0f} s for the whole process "
            f"(imports included). Its line: `{cl['line']}`"
            + (f" Load average {cl['loads'][0]} at the start, {cl['loads'][1]} at the end." if "loads" in cl else ""),
        ]
    return lines


def _merge(parts: list[dict]) -> dict:
    """One raw record from several --raw files: the speed invocations' rounds concatenated
    (best-of is taken over all), their commands and loads listed, setup times their best;
    the other parts' keys (agreement_run, cli) as given."""
    raw: dict = {}
    speed = [p for p in parts if "runs" in p]
    for p in parts:
        raw.update({k: v for k, v in p.items() if k not in ("runs", "loads", "setup_s", "command")})
    if speed:
        raw.update(speed[-1])
        raw["runs"] = {name: [r for p in speed for r in p["runs"][name]] for name in speed[0]["runs"]}
        # A record merged before keeps its invocations' commands and loads.
        raw["commands"] = [c for p in speed for c in p.get("commands", [p.get("command", "")])]
        raw["load_runs"] = [lo for p in speed for lo in p.get("load_runs", [p["loads"]])]
        raw["costs"] = dict(min((p["costs"] for p in speed), key=lambda c: c["mj_step_us"]))  # the least disturbed
        scaling = [
            x
            for p in speed
            for x in p["costs"].get("physics_scalings")
            or ([p["costs"]["physics_scaling"]] if p["costs"].get("physics_scaling") else [])
        ]
        raw["costs"]["physics_scaling"] = scaling[0] if scaling else None
        raw["costs"]["physics_scalings"] = scaling
        raw["setup_s"] = {
            k: min(p.get("setup_s", {}).get(k, float("inf")) for p in speed) for k in speed[-1].get("setup_s", {})
        }
        for p in parts:
            for key in ("agreement_run", "cli"):
                if p.get(key):
                    raw[key] = p[key]
    return raw


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--designs", type=int, default=1024)
    p.add_argument("--oracle-designs", type=int, default=48)
    p.add_argument("--motion", default="toss:100")
    p.add_argument("--steps", type=int, default=50, help="control steps of the motion (0: all)")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--cli", action="store_true", help="also time `tt rollout --backend mjbatch` in a subprocess")
    p.add_argument("--part", choices=("speed", "agreement", "cli"), default="speed")
    p.add_argument("--agreement-designs", type=int, default=100)
    p.add_argument("--agreement-motions", type=int, default=5)
    p.add_argument("--raw", type=Path, default=None, help="write the measurements as JSON")
    p.add_argument(
        "--from-raw", type=Path, nargs="+", default=None, help="rewrite the report from --raw files (speed, agreement)"
    )
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/quadruped_batched.md"))
    args = p.parse_args()
    command = "python " + " ".join(sys.argv)
    if args.from_raw:
        raw = _merge([json.loads(path.read_text()) for path in args.from_raw])
    elif args.part == "agreement":
        raw = {"agreement_run": {**run_agreement(args), "command": command}}
    elif args.part == "cli":
        loads = [load_line()]
        raw = {"cli": _cli(args.designs, args.motion, max(args.threads))}
        raw["cli"]["loads"] = [*loads, load_line()]
    else:
        raw = run(args)
        raw["command"] = command
    if args.raw:  # with --from-raw: the merged record
        args.raw.write_text(json.dumps(raw, indent=1))
    if "runs" not in raw:
        print(f"{args.part} measured; merge it into the report with --from-raw SPEED.json {args.raw}")
        return
    print(f"wrote {write_report(args.out, report(raw, raw.get('command', command)))}")


if __name__ == "__main__":
    main()
