"""Rollout speed: world-steps per second of every backend, side by side in one process.

Workload: N random ViperX designs (seed 0, nested: N = 64 is the first 64 of the largest N)
x the toss (223 control steps at 50 Hz, 10 physics steps of 0.002 s each); a world-step is
one physics step of one world. Every backend runs the same compiled MjModels:

* oracle: MuJoCo C + mink (`tt.sim.validate`), one world after another; measured on
  ``--oracle-worlds`` designs (>= 32 by default), its per-world rate holds at every N. It
  stops a world at termination, so only executed steps count.
* mujoco.rollout: MuJoCo C's threaded open-loop rollout with every core, physics only,
  under piecewise-constant commands (new targets every 0.1 s): the C ceiling without a
  controller. At large N it steps fewer than the toss's 2,230 physics steps
  (``--mujoco-world-steps`` per size; its rate does not depend on the episode length).
* warp: tt's fused kernels (`tt.kernels.rollout.rollout_tree`, controller + physics +
  records), at every thread count of ``--threads`` (default 1, 2, 4, ... and every core).
  Its rate is timed between the ends of the first and the last 50-step launch chunk of
  each topology group, so it leaves out model building and the start posture (reported
  under setup), and the thread counts share one built model.
* mjwarp, newton: MuJoCo-Warp and Newton through `tt.sim.rollout.rollout`, rate from a
  short and a long run (the difference cancels setup), each within ``--budget`` s; they
  run last, in whatever is left of ``--deadline``.

The CLI figure: `tt rollout --design designs.json` in a fresh process at N = ``--cli-n``
for 1 and all threads, against `--backend mujoco` on ``--oracle-worlds`` designs, as the
CLI reports it (model building, Warp module cache load, rollout and scoring included).

The load average is recorded at the start, with every measurement and at the end: on a
shared machine every rate is a lower bound. A projection to 32 cores is labelled as one.

Writes ``--out`` (default benchmarks/results/sim.md). Usage:
    python benchmarks/sim.py                # the full run: about 7-9 min on an idle 2-core machine
    python benchmarks/sim.py --quick        # smoke test of every path: tiny sizes, short motion
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

try:
    from machine import machine_header
except ImportError:  # run as a module from the repository root
    from benchmarks.machine import machine_header

SUBSTEPS = 10  # physics steps per control step (0.002 s physics, 50 Hz control)
SHORT_STEPS = 10  # control steps of the short run (mjwarp, newton)
CHUNK = 50  # control steps per warp launch (tt.sim.rollout.DEFAULT_CHUNK)
OTHERS = ("mjwarp", "newton")
#: Targets of the issue at N = 4,096 (ratios of world-steps/s).
TARGETS = {"vs_mujoco_rollout": 2.5, "vs_oracle": 15.0, "thread_speedup": 1.8}


def _log(record: dict) -> dict:
    """One machine-readable line per measurement, with the load average when it was taken."""
    record = {**record, "load1": round(os.getloadavg()[0], 2)}
    print(json.dumps(record), flush=True)
    return record


def _cores() -> int:
    from tt.kernels.rollout import cpu_threads

    return cpu_threads()


def _toss(steps: int | None = None):
    from tt.sim.motions import for_space, get_motion
    from tt.sim.motions.base import Motion

    toss = for_space([get_motion("toss")], "viperx")[0]
    if steps is None or steps >= toss.steps:
        return toss
    return Motion(f"toss[:{steps}]", toss.pos[:steps], toss.quat[:steps], toss.dt)


# --------------------------------------------------------------------------- measurements


def _oracle(models, motion) -> dict:
    from tt.sim.rollout import rollout

    start = time.perf_counter()
    ep = rollout(models, [motion], backend="mujoco")
    seconds = time.perf_counter() - start
    alive = ep.alive.numpy()
    # Executed control steps: the alive ones, plus the step that terminated a world early.
    executed = int(alive.sum() + np.sum(alive.sum(axis=1) < motion.steps))
    world_steps = executed * SUBSTEPS
    return _log({"backend": "oracle", "worlds": len(models), "world_steps": world_steps, "seconds": seconds,
                 "rate": world_steps / seconds})  # fmt: skip


def _mujoco_rollout(models, physics_steps: int, threads: int, chunk: int = 256) -> dict:
    """MuJoCo C's threaded rollout: physics only, open loop; one call per structure group
    and chunk of worlds (bounds the state output's memory)."""
    import mujoco
    from mujoco import rollout as mj_rollout

    from tt.sim.mjwarp_backend import structure_key

    groups: dict[tuple, list[int]] = {}
    for i, m in enumerate(models):
        groups.setdefault(structure_key(m), []).append(i)
    rng = np.random.default_rng(0)
    seconds = 0.0
    with mj_rollout.Rollout(nthread=threads) as pool:
        for members in groups.values():
            m0 = models[members[0]]
            datas = [mujoco.MjData(m0) for _ in range(threads)]
            spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
            state0 = np.zeros(mujoco.mj_stateSize(m0, spec))
            mujoco.mj_getState(m0, datas[0], state0, spec)
            for lo in range(0, len(members), chunk):
                ids = members[lo : lo + chunk]
                group = [models[i] for i in ids]
                knots = physics_steps // 50 + 1
                ctrl = np.zeros((len(ids), physics_steps, m0.nu))
                for k, m in enumerate(group):
                    low, high = m.actuator_ctrlrange.T
                    ctrl[k] = np.repeat(rng.uniform(low, high, (knots, m.nu)), 50, axis=0)[:physics_steps]
                initial = np.tile(state0, (len(ids), 1))
                start = time.perf_counter()
                pool.rollout(group, datas, initial, ctrl)
                seconds += time.perf_counter() - start
    world_steps = len(models) * physics_steps
    return _log({"backend": "mujoco.rollout", "threads": threads, "worlds": len(models), "physics_steps": physics_steps,
                 "world_steps": world_steps, "seconds": seconds, "rate": world_steps / seconds})  # fmt: skip


def _warp_groups(models, motion):
    """Per topology group of `models`: the built `TreeModel` and its build time; the toss's
    `MotionArrays`."""
    from tt.kernels.model import build_tree_model, topology_key
    from tt.kernels.rollout import motion_arrays
    from tt.sim.designs import get_space

    sites = get_space("viperx").ee_sites()
    groups: dict[tuple, list] = {}
    for m in models:
        groups.setdefault(topology_key(m, sites), []).append(m)
    built = []
    for members in groups.values():
        start = time.perf_counter()
        tree = build_tree_model(members, sites, device="cpu")
        built.append((tree, len(members), time.perf_counter() - start))
    marrays = motion_arrays(motion.pos[None], motion.quat[None], [motion.steps], device="cpu")
    return built, marrays


def _warp(built, marrays, steps: int, threads: int, repeats: int) -> dict:
    """Stepping rate of tt's fused kernels: world-steps of the launch chunks after each group's
    first, over the time from the end of its first chunk to the end of its last (the best
    of `repeats` runs); setup: build time + start posture + the first chunk less its share
    of stepping. ``rate`` counts every world's every step, as `tt rollout` does; a world
    past termination only repeats its last record, so ``rate_executed`` counts the steps
    that ran physics (the oracle's count)."""
    from tt.kernels.rollout import rollout_tree
    from tt.sim.controller import IKConfig

    best = None
    for _ in range(repeats):
        stepped, executed, timed, first_chunks, calls = 0, 0, 0.0, 0.0, 0.0
        for tree, n, _build in built:
            marks: list[float] = []
            start = time.perf_counter()
            out = rollout_tree(tree, marrays, n, steps, **IKConfig().rollout_args(), chunk=CHUNK, threads=threads,
                               device="cpu", progress=lambda k: marks.append(time.perf_counter()))  # fmt: skip
            calls += time.perf_counter() - start
            if len(marks) < 2:
                raise ValueError(f"the warp rate needs at least two launch chunks: give >= {CHUNK + 1} control steps")
            alive = out.alive.numpy().sum(axis=1)
            ran = alive + (alive < steps)  # the alive steps and the one that terminated a world
            stepped += n * SUBSTEPS * (steps - CHUNK)
            executed += int(np.clip(ran - CHUNK, 0, steps - CHUNK).sum()) * SUBSTEPS
            timed += marks[-1] - marks[0]
            first_chunks += marks[0] - start
        run = (stepped / timed, first_chunks, calls, executed / timed, executed / stepped)
        best = run if best is None or run[0] > best[0] else best
    rate, first_chunks, calls, rate_executed, share = best
    worlds = sum(n for _, n, _ in built)
    build = sum(b for _, _, b in built)
    setup = build + max(first_chunks - worlds * SUBSTEPS * min(CHUNK, steps) / rate, 0.0)
    return _log({"backend": "warp", "threads": threads, "worlds": worlds, "groups": len(built), "control_steps": steps,
                 "rate": rate, "rate_executed": rate_executed, "executed_share": share, "setup_s": setup,
                 "build_s": build, "seconds": calls})  # fmt: skip


def _closed_loop(backend: str, designs, steps: int) -> float:
    from tt.sim.rollout import rollout

    motion = _toss(steps)
    start = time.perf_counter()
    rollout(designs, [motion], backend=backend, device="cpu")
    return time.perf_counter() - start


def _closed_loop_rate(backend: str, designs, full_steps: int, budget: float) -> dict:
    """mjwarp / newton: rate from a short and a long run (the difference cancels setup); the
    long run is cut to fit `budget` seconds."""
    n = len(designs)
    short = _closed_loop(backend, designs, SHORT_STEPS)
    per_step = short / SHORT_STEPS  # an upper bound: includes setup
    long_steps = full_steps
    if short + long_steps * per_step > budget:
        long_steps = min(full_steps, int(max(3 * SHORT_STEPS, (budget - short) / per_step)))
    long = _closed_loop(backend, designs, long_steps)
    if long < 2.0:  # fast combinations: the best of 3 of each run
        short = min([short] + [_closed_loop(backend, designs, SHORT_STEPS) for _ in range(2)])
        long = min([long] + [_closed_loop(backend, designs, long_steps) for _ in range(2)])
    gap = long - short
    if gap <= 0.05 * long:
        # The extra steps took no measurable time next to setup: no rate can be read off.
        return _log(
            {
                "backend": backend,
                "worlds": n,
                "rate": None,
                "control_steps": long_steps,
                "truncated": long_steps < full_steps,
                "setup_s": short,
                "unmeasurable": True,
            }
        )
    rate = n * SUBSTEPS * (long_steps - SHORT_STEPS) / gap
    return _log(
        {
            "backend": backend,
            "worlds": n,
            "rate": rate,
            "control_steps": long_steps,
            "truncated": long_steps < full_steps,
            "setup_s": max(short - n * SUBSTEPS * SHORT_STEPS / rate, 0.0),
        }
    )


_CLI_RATE = re.compile(r"(\d+) worlds, ([\d,]+) world-steps in ([\d.]+) s: ([\d,]+) world-steps/s")


_BREAKDOWN = """
import json, sys, time
import warp as wp
wp.config.quiet = True
from tt.baselines.evaluate import score_episode
from tt.kernels.rollout import rollout_kernels
from tt.sim.designs import get_space, load_designs
from tt.sim.motions import get_motion, load_npz
from tt.sim.rollout import rollout
path, threads, motion_file = sys.argv[1], int(sys.argv[2]), sys.argv[3]
motions = [load_npz(motion_file) if motion_file else get_motion("toss")]
designs = load_designs(path)
space = get_space(designs[0].space)
out = {}
t = time.perf_counter(); trees = space.trees(designs); out["tree fields (`space.trees`)"] = time.perf_counter() - t
t = time.perf_counter()
for _, fields in trees.groups:
    wp.load_module(rollout_kernels(fields.topology).module, device="cpu")
out[f"Warp module hash + cache load ({len(trees.groups)} topologies)"] = time.perf_counter() - t
t = time.perf_counter(); ep = rollout(trees, motions, device="cpu", threads=threads)
out["rollout: TreeModel upload, start posture, stepping"] = time.perf_counter() - t
t = time.perf_counter()
score_episode(ep, designs, motions, "tracking", models=trees)
out["scoring"] = time.perf_counter() - t
print(json.dumps(out))
"""


def _cli_breakdown(designs_json: Path, threads: int, motion_file: Path | None) -> dict:
    """Seconds of each step of a warp `tt rollout` call, in a fresh process (`_BREAKDOWN`)."""
    proc = subprocess.run(
        [sys.executable, "-c", _BREAKDOWN, str(designs_json), str(threads), str(motion_file or "")],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"the CLI breakdown failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return _log({"cli_breakdown_threads": threads, **json.loads(proc.stdout.strip().splitlines()[-1])})


def _cli(designs_json: Path, backend: str, threads: int | None, motion_file: Path | None) -> dict:
    """`tt rollout --design designs.json` in a fresh process; the rate it prints."""
    args = [sys.executable, "-c", "from tt.cli import main; main()", "rollout", "--design", str(designs_json),
            "--backend", backend, "--device", "cpu"]  # fmt: skip
    if threads is not None:
        args += ["--threads", str(threads)]
    if motion_file is not None:
        args += ["--motion", str(motion_file)]
    start = time.perf_counter()
    proc = subprocess.run(args, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    match = _CLI_RATE.search(proc.stdout)
    if proc.returncode != 0 or match is None:
        raise RuntimeError(
            f"`tt rollout` failed (exit {proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
        )
    worlds, steps, seconds, rate = match.groups()
    return _log({"cli": backend, "threads": threads, "worlds": int(worlds), "world_steps": int(steps.replace(",", "")),
                 "seconds": float(seconds), "rate": float(rate.replace(",", "")), "process_wall_s": wall})  # fmt: skip


# --------------------------------------------------------------------------- report


def _fmt_rate(rate: float | None) -> str:
    if rate is None or rate != rate or rate == float("inf"):
        return "-"
    if rate >= 1e6:
        return f"{rate / 1e6:.2f} M"
    if rate >= 1e3:
        return f"{rate / 1e3:.1f} k"
    return f"{rate:.0f}"


def _row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _check(value: float | None, target: float) -> str:
    if value is None:
        return "not measured"
    return f"{value:.2f}x (target >= {target}x: {'met' if value >= target else 'NOT met'})"


def _report(args, r: dict) -> str:
    from tt.sim.designs.base import PARALLEL_MODELS_MIN

    sizes, threads, cores = args.sizes, args.threads, r["cores"]
    top = max(threads)
    lines = [_row(["backend"] + [f"N = {n}" for n in sizes]), "|" + "---|" * (len(sizes) + 1)]
    oracle = r["oracle"]["rate"]
    lines.append(_row([f"oracle (MuJoCo C + mink, one world at a time; {r['oracle']['worlds']} worlds)"]
                      + [_fmt_rate(oracle)] * len(sizes)))  # fmt: skip
    lines.append(_row([f"mujoco.rollout (C, {cores} threads, physics only, open loop)"]
                      + [_fmt_rate(r["mujoco"][n]["rate"]) for n in sizes]))  # fmt: skip
    for k in threads:
        lines.append(_row([f"warp, tt's fused kernels (closed loop), {k} thread{'s' if k > 1 else ''}"]
                          + [_fmt_rate(r["warp"][n][k]["rate"]) for n in sizes]))  # fmt: skip
    lines.append(_row([f"warp, {top} thread{'s' if top > 1 else ''}, executed world-steps only"]
                      + [_fmt_rate(r["warp"][n][top]["rate_executed"]) for n in sizes]))  # fmt: skip
    lines.append(_row(["share of warp world-steps executed (the rest repeat a terminated world's record)"]
                      + [f"{100 * r['warp'][n][top]['executed_share']:.0f} %" for n in sizes]))  # fmt: skip
    notes = []
    for b in OTHERS:
        if b not in args.backends:
            continue
        cells = []
        for n in sizes:
            rec = r["others"].get((b, n))
            if rec is None or "rate" not in rec:
                cells.append("skipped")
                if rec is not None:
                    notes.append(f"- {b}, N = {n}: skipped: {rec['skipped']}.")
                continue
            cells.append(_fmt_rate(rec["rate"]) + (" *" if rec["truncated"] else ""))
            if rec["truncated"]:
                notes.append(f"- {b}, N = {n}: * toss cut to its first {rec['control_steps']} control steps.")
        lines.append(_row([f"{b} (closed loop, 1 Warp CPU thread)"] + cells))
    for n in sizes:
        rec = r["mujoco"][n]
        if rec["physics_steps"] < r["full_steps"] * SUBSTEPS:
            notes.append(
                f"- mujoco.rollout, N = {n}: {rec['physics_steps']} of the toss's "
                f"{r['full_steps'] * SUBSTEPS} physics steps."
            )
    rates = "\n".join(lines)

    ratio = [_row(["ratio"] + [f"N = {n}" for n in sizes]), "|" + "---|" * (len(sizes) + 1)]
    ratio.append(_row([f"warp ({top} threads) / mujoco.rollout ({cores} threads)"]
                      + [f"{r['warp'][n][top]['rate'] / r['mujoco'][n]['rate']:.2f}x" for n in sizes]))  # fmt: skip
    ratio.append(
        _row([f"warp ({top} threads) / oracle"] + [f"{r['warp'][n][top]['rate'] / oracle:.1f}x" for n in sizes])
    )
    ratio.append(_row(["the same on executed world-steps only: warp / mujoco.rollout"]
                      + [f"{r['warp'][n][top]['rate_executed'] / r['mujoco'][n]['rate']:.2f}x"
                         for n in sizes]))  # fmt: skip
    ratio.append(_row(["the same on executed world-steps only: warp / oracle"]
                      + [f"{r['warp'][n][top]['rate_executed'] / oracle:.1f}x" for n in sizes]))  # fmt: skip
    for k in threads[1:]:
        ratio.append(_row([f"warp speed-up, 1 -> {k} threads"]
                          + [f"{r['warp'][n][k]['rate'] / r['warp'][n][1]['rate']:.2f}x" for n in sizes]))  # fmt: skip
    ratios = "\n".join(ratio)

    setup = [_row(["N", "MuJoCo models (MJCF + compile) [s]", "tree fields without MJCF (`space.trees`) [s]",
                   "warp setup: TreeModel + start posture [s]", "warp stepping, 1 thread [s]"]),
             "|---|---|---|---|---|"]  # fmt: skip
    for n in sizes:
        w = r["warp"][n][1]
        trees = r["trees_s"].get(n)
        setup.append(_row([n, f"{r['build_s_per_design'] * n:.2f}", "-" if trees is None else f"{trees:.2f}",
                           f"{w['setup_s']:.2f}", f"{n * SUBSTEPS * r['full_steps'] / w['rate']:.2f}"]))  # fmt: skip
    setup_t = "\n".join(setup)

    # Per-core cost and a projection.
    n_ref = 4096 if 4096 in sizes else max(sizes)
    one, many = r["warp"][n_ref][1]["rate"], r["warp"][n_ref][top]["rate"]
    efficiency = many / (top * one) if top > 1 else 1.0
    scaling = [
        _row(["threads", f"warp world-steps/s at N = {n_ref}", "per thread", "parallel efficiency"]),
        "|---|---|---|---|",
    ]
    for k in threads:
        rate = r["warp"][n_ref][k]["rate"]
        scaling.append(_row([k, _fmt_rate(rate), _fmt_rate(rate / k), f"{rate / (k * one):.2f}"]))
    scaling.append(_row(["32 (PROJECTION, not measured)", _fmt_rate(32 * one * efficiency), _fmt_rate(one * efficiency),
                         f"{efficiency:.2f} (assumed: the {top}-thread efficiency)"]))  # fmt: skip
    scaling_t = "\n".join(scaling)

    targets = []
    if 4096 in sizes:
        w, m = r["warp"][4096], r["mujoco"][4096]["rate"]
        targets += [
            f"- warp ({top} threads) / mujoco.rollout ({cores} threads): "
            f"{_check(w[top]['rate'] / m, TARGETS['vs_mujoco_rollout'])}",
            f"- warp ({top} threads) / oracle: {_check(w[top]['rate'] / oracle, TARGETS['vs_oracle'])}",
            f"- on executed world-steps only: warp / mujoco.rollout "
            f"{_check(w[top]['rate_executed'] / m, TARGETS['vs_mujoco_rollout'])}, warp / oracle "
            f"{_check(w[top]['rate_executed'] / oracle, TARGETS['vs_oracle'])}",
            f"- warp 1 -> {top} threads: "
            f"{_check(w[top]['rate'] / w[1]['rate'] if top > 1 else None, TARGETS['thread_speedup'])}",
        ]
    cli_t = ""
    if r.get("cli"):
        c = r["cli"]
        rows = [
            _row(["command", "worlds", "world-steps/s (as printed, setup included)", "process wall [s]"]),
            "|---|---|---|---|",
        ]
        for rec in c["warp"].values():
            spread = rec.get("rates", [rec["rate"]])
            rate = _fmt_rate(rec["rate"]) + (
                f" (median of {len(spread)}: {_fmt_rate(spread[0])} - {_fmt_rate(spread[-1])})"
                if len(spread) > 1
                else ""
            )
            rows.append(_row([f"`tt rollout --design designs.json --threads {rec['threads']}`", rec["worlds"], rate,
                              f"{rec['process_wall_s']:.1f}"]))  # fmt: skip
        o = c["mujoco"]
        rows.append(_row(["`tt rollout --design designs.json --backend mujoco`", o["worlds"], _fmt_rate(o["rate"]),
                          f"{o['process_wall_s']:.1f}"]))  # fmt: skip
        n_cli = args.cli_n
        best = c["warp"][top]["rate"]
        mref = r["mujoco"].get(n_cli, {}).get("rate")
        cli_checks = [
            f"- CLI warp ({top} threads) / CLI oracle: {_check(best / o['rate'], TARGETS['vs_oracle'])}",
            f"- CLI warp ({top} threads) / mujoco.rollout ({cores} threads, N = {n_cli}, stepping only): "
            + _check(best / mref if mref else None, TARGETS["vs_mujoco_rollout"]),
            f"- CLI warp 1 -> {top} threads: "
            f"{_check(best / c['warp'][1]['rate'] if top > 1 else None, TARGETS['thread_speedup'])}",
        ]
        if mref:
            # mujoco.rollout cannot run without the MuJoCo models it steps; with their build
            # (in worker processes, as measured above) on its clock too:
            steps_n = n_cli * SUBSTEPS * r["full_steps"]
            with_build = steps_n / (n_cli * r["build_s_per_design"] + steps_n / mref)
            cli_checks.append(
                f"- for reference, not the target: CLI warp / mujoco.rollout with its model building "
                f"({_fmt_rate(with_build)} world-steps/s): {best / with_build:.2f}x"
            )
        parts = c.get("breakdown")
        if parts:
            cli_checks += [
                "",
                f"Where a {top}-thread call's evaluation time goes (a fresh process running the same "
                "steps as the CLI, timed one after another):",
                "",
                _row(["step", "seconds"]),
                "|---|---|",
            ]
            cli_checks += [
                _row([k, f"{v:.2f}"]) for k, v in parts.items() if k not in ("load1", "cli_breakdown_threads")
            ]
        cli_t = (
            f"## Through the CLI, setup included (N = {n_cli})\n\n"
            "Each command runs in a fresh process; the rate is what `tt rollout` prints: world-steps over the "
            "time of the evaluation (loading designs.json excluded; model building (tree fields for warp), Warp "
            "module hash and cache load, rollout and scoring included).\n\n"
            + "\n".join(rows)
            + "\n\n"
            + "\n".join(cli_checks)
            + "\n\n"
        )
    lb, la = r["load_before"], r["load_after"]
    loads = [rec["load1"] for rec in r["records"] if "load1" in rec]
    text = (
        "# Rollout speed: world-steps per second\n\n" + machine_header("cpu") + f"- command: `{r['command']}`\n"
        f"- load average (1, 5, 15 min): {lb[0]:.1f}, {lb[1]:.1f}, {lb[2]:.1f} at the start, {la[0]:.1f}, {la[1]:.1f}, "
        f"{la[2]:.1f} at the end, 1-min load {min(loads):.1f}-{max(loads):.1f} during the measurements "
        f"(on {cores} cores; above ~0 other jobs competed and every rate is a lower bound); "
        f"{r['wall'] / 60:.1f} min wall\n"
        f"- workload: N random ViperX designs (seed 0, nested) x {r['motion']} ({r['full_steps']} control "
        "steps at 50 Hz, "
        f"{SUBSTEPS} physics steps of 0.002 s each); a world-step is one physics step of one world; all backends run "
        "the same compiled MjModels in this one process\n\n"
        "## World-steps per second\n\n"
        + rates
        + "\n\n"
        + ("\n".join(notes) + "\n\n" if notes else "")
        + "The oracle's rate holds at every N (it runs one world after another) and counts the steps it executed "
        "(it stops a world at termination). mujoco.rollout is physics only (no controller, no records) and steps "
        "every world. warp, mjwarp and newton run the oracle's controller at 50 Hz and record Episodes; their rates "
        "count every world's every step, as `tt rollout` does, although a world past termination only repeats its "
        "last record: the warp rows on executed world-steps are the like-for-like comparison with the oracle. "
        "warp's rate excludes setup (next tables).\n\n"
        "## Ratios\n\n"
        + ratios
        + "\n\n"
        + ("## Targets at N = 4,096\n\n" + "\n".join(targets) + "\n\n" if targets else "")
        + cli_t
        + f"## Thread scaling at N = {n_ref}\n\n"
        + scaling_t
        + "\n\n"
        "The 32-core row is a projection, not a measurement: the 1-thread rate times 32 times the measured "
        f"{top}-thread parallel efficiency (it assumes the per-core rate and that efficiency hold on 32 cores).\n\n"
        "## Setup\n\n"
        f"Model building is `space.models(designs, processes={cores})` (MJCF text + MuJoCo compile, in worker "
        f"processes from {PARALLEL_MODELS_MIN} designs on; {1000 * r['build_s_per_design']:.2f} ms per design here, "
        "measured once on all the designs): what the oracle, mjwarp and newton need, and this benchmark's "
        "in-process rows. `tt rollout --backend warp` (the CLI rows) builds no MuJoCo model per design: "
        "`space.trees` writes the kernels' model fields for all designs of a topology at once with numpy, from "
        "one compiled template per topology (tests/test_chain_tree.py holds them to MuJoCo's compile); its time "
        "is measured on the first N designs. Warp setup is the TreeModel upload per topology group plus the "
        "start-posture kernel (50 float64 IK steps per world).\n\n" + setup_t + "\n"
    )
    return text


# --------------------------------------------------------------------------- main


def _thread_counts(cores: int) -> list[int]:
    counts, k = [], 1
    while k < cores:
        counts.append(k)
        k *= 2
    return counts + [cores]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 1024, 4096, 16384])
    ap.add_argument(
        "--threads", type=int, nargs="+", default=None, help="warp thread counts (default 1, 2, 4, ..., all)"
    )
    ap.add_argument("--oracle-worlds", type=int, default=32)
    ap.add_argument(
        "--mujoco-world-steps",
        type=float,
        default=8e6,
        help="world-steps per mujoco.rollout size (at least 1,000 physics steps)",
    )
    ap.add_argument(
        "--backends",
        nargs="*",
        default=None,
        help="besides oracle, mujoco.rollout and warp: any of mjwarp, newton (default both; --quick: none)",
    )
    ap.add_argument("--others-max-n", type=int, default=1024, help="largest N for mjwarp and newton")
    ap.add_argument("--budget", type=float, default=20.0, help="seconds per mjwarp / newton combination")
    ap.add_argument("--deadline", type=float, default=480.0, help="mjwarp / newton are skipped past this many seconds")
    ap.add_argument(
        "--cli-n", type=int, default=None, help="designs of the CLI figure (default 4096, --quick: 8; 0: none)"
    )
    ap.add_argument(
        "--cli-repeats",
        type=int,
        default=None,
        help="fresh `tt rollout` processes per warp thread count, interleaved; the median counts (the lower "
        "middle one for an even count); default 3, --quick: 1",
    )
    ap.add_argument(
        "--warp-repeats",
        type=int,
        default=None,
        help="in-process warp runs per N and thread count, the fastest counts (default: 3 below 2M "
        "world-steps, else 1)",
    )
    ap.add_argument("--steps", type=int, default=None, help="control steps of the toss (default: all 223)")
    ap.add_argument(
        "--quick", action="store_true", help="smoke test: N = 1, 8; 60 control steps; 2 oracle worlds; CLI on 8"
    )
    ap.add_argument(
        "--out", type=Path, default=None, help="report file (default benchmarks/results/sim.md; --quick: a temp file)"
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.sizes, args.oracle_worlds = [1, 8], 2
        args.cli_n = 8 if args.cli_n is None else args.cli_n
        args.steps = args.steps or CHUNK + 10
        args.mujoco_world_steps, args.budget, args.others_max_n = 2e4, 5.0, 1
    args.sizes = sorted(set(args.sizes))
    args.cli_n = 4096 if args.cli_n is None else args.cli_n
    args.cli_repeats = (1 if args.quick else 3) if args.cli_repeats is None else args.cli_repeats
    if args.cli_repeats < 1:
        ap.error(f"--cli-repeats {args.cli_repeats}: must be >= 1")
    if args.warp_repeats is not None and args.warp_repeats < 1:
        ap.error(f"--warp-repeats {args.warp_repeats}: must be >= 1")
    if args.backends is None:
        args.backends = [] if args.quick else list(OTHERS)
    for b in args.backends:
        if b not in OTHERS:
            ap.error(f"--backends {b!r}: choose from {list(OTHERS)}")
    if args.out is None:
        args.out = (
            Path(tempfile.mkdtemp(prefix="tt_sim_quick_")) / "sim.md"
            if args.quick
            else Path(__file__).parent / "results" / "sim.md"
        )

    import warp as wp

    wp.config.quiet = True
    from tt.sim.designs import get_space, save_designs

    begin = time.perf_counter()
    load_before = os.getloadavg()
    cores = _cores()
    args.threads = sorted(set(args.threads or _thread_counts(cores)) | {1})
    space = get_space("viperx")
    motion = _toss(args.steps)
    full = motion.steps
    designs = space.sample(max(args.sizes + [args.oracle_worlds, args.cli_n]), seed=0)
    start = time.perf_counter()
    models = space.models(designs[: max(args.sizes + [args.oracle_worlds])], processes=cores)
    build_per_design = (time.perf_counter() - start) / len(models)
    trees_s = {}
    space.trees(designs[:1])  # first-call imports out of the timings
    for n in args.sizes:
        start = time.perf_counter()
        space.trees(designs[:n])
        trees_s[n] = time.perf_counter() - start
    records: list[dict] = [
        _log({"model_building_s_per_design": build_per_design, "designs": len(models), "processes": cores})
    ]

    # Load every warp module once (from the cache), so that no timing below compiles.
    from tt.sim.rollout import rollout

    rollout(models[:64], [_toss(2)], device="cpu", threads=1)

    results: dict = {"cores": cores, "full_steps": full, "motion": motion.name, "build_s_per_design": build_per_design,
                     "trees_s": trees_s,
                     "load_before": load_before, "records": records,
                     "mujoco": {}, "warp": {}, "others": {}}  # fmt: skip
    results["oracle"] = _oracle(models[: args.oracle_worlds], motion)
    records.append(results["oracle"])
    for n in args.sizes:
        physics = min(full * SUBSTEPS, max(1000, int(args.mujoco_world_steps / n)))
        results["mujoco"][n] = _mujoco_rollout(models[:n], physics, cores)
        records.append(results["mujoco"][n])
        built, marrays = _warp_groups(models[:n], motion)
        results["warp"][n] = {}
        for k in args.threads:
            repeats = args.warp_repeats or (3 if n * full * SUBSTEPS < 2e6 else 1)
            results["warp"][n][k] = _warp(built, marrays, full, k, repeats)
            records.append(results["warp"][n][k])
        del built, marrays

    if args.cli_n:
        with tempfile.TemporaryDirectory(prefix="tt_sim_cli_") as tmp:
            tmp = Path(tmp)
            save_designs(designs[: args.cli_n], tmp / "designs.json")
            save_designs(designs[: args.oracle_worlds], tmp / "oracle.json")
            motion_file = None
            if motion.steps < _toss().steps:
                from tt.sim.motions import save_npz

                motion_file = tmp / "motion.npz"
                save_npz(motion, motion_file)
            cli = {"warp": {}}
            # Fresh processes vary by tens of percent on a shared box: each thread count
            # runs cli_repeats times, interleaved so drift meets every count alike; the
            # median run stands for it.
            runs: dict[int, list[dict]] = {k: [] for k in sorted({1, max(args.threads)})}
            for _ in range(args.cli_repeats):
                for k in runs:
                    runs[k].append(_cli(tmp / "designs.json", "warp", k, motion_file))
                    records.append(runs[k][-1])
            for k, rs in runs.items():
                rs = sorted(rs, key=lambda rec: rec["rate"])
                cli["warp"][k] = {**rs[(len(rs) - 1) // 2], "rates": [rec["rate"] for rec in rs]}
            cli["mujoco"] = _cli(tmp / "oracle.json", "mujoco", None, motion_file)
            try:
                cli["breakdown"] = _cli_breakdown(tmp / "designs.json", max(args.threads), motion_file)
                records.append(cli["breakdown"])
            except RuntimeError as e:  # the table is left out; the run's other figures stand
                print(f"warning: {e}", file=sys.stderr, flush=True)
            records.append(cli["mujoco"])
            results["cli"] = cli

    # mjwarp and newton last, in what is left of the deadline.
    for b in args.backends:
        left = args.deadline - (time.perf_counter() - begin)
        if left < 3 * args.budget:  # its module load (a compile, when not cached) must fit too
            for n in args.sizes:
                results["others"][(b, n)] = {"skipped": f"{left:.0f} s left of the {args.deadline:.0f} s deadline"}
            continue
        try:
            # Designs, not models: Newton imports each design's MJCF (the same models).
            _closed_loop(b, designs[:1], 2)  # module load (or compile) outside the timings
        except Exception as e:  # noqa: BLE001 - a backend that cannot run is reported, not fatal
            for n in args.sizes:
                results["others"][(b, n)] = {"skipped": f"{type(e).__name__}: {e}"}
            continue
        for n in args.sizes:
            left = args.deadline - (time.perf_counter() - begin)
            if n > args.others_max_n:
                results["others"][(b, n)] = {"skipped": f"N > --others-max-n {args.others_max_n}"}
            elif left < args.budget:
                results["others"][(b, n)] = {"skipped": f"{left:.0f} s left of the {args.deadline:.0f} s deadline"}
            else:
                results["others"][(b, n)] = _closed_loop_rate(b, designs[:n], full, args.budget)
                records.append(results["others"][(b, n)])

    results["load_after"] = os.getloadavg()
    results["wall"] = time.perf_counter() - begin
    results["command"] = "python benchmarks/sim.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = _report(args, results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    print(f"wrote {args.out}", flush=True)


if __name__ == "__main__":
    main()
