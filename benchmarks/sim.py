"""Rollout speed: world-steps per second of every backend on N random ViperX designs x the toss.

A world-step is one physics step (0.002 s) of one world; the toss is 223 control steps of
10 physics steps each. Backends, measured in one run:

* oracle: MuJoCo C + mink (`tt.sim.validate`), one robot at a time in Python; measured
  on a few worlds, its per-world rate holds at every N (it does not batch). It stops a
  world at termination, so only executed steps count.
* mujoco.rollout: MuJoCo C's threaded open-loop rollout (2 threads), physics only, the same
  models under piecewise-constant commands (new targets every 0.1 s): the C ceiling
  without a controller.
* mjwarp, newton, warp: tt's closed-loop rollouts (`tt.sim.rollout.rollout`) on the Warp
  CPU device: MuJoCo-Warp, Newton Featherstone, tt's fused kernels. They step every world
  for the whole motion.

The closed-loop rates exclude setup (model building, start posture): each combination
runs a short motion (the first 10 control steps) and a long one (the whole toss, or as
many steps as fit the time budget), and the rate is the difference in world-steps over the
difference in time (runs shorter than 2 s: the best of 5); setup is the short run's time
less its share of stepping. Compile
times come from a separate process per backend with an empty Warp kernel cache: the first
call (compile + run) and a second, warm call, on one design of each ViperX topology.

Writes benchmarks/results/sim.md. Usage:
    python benchmarks/sim.py [--sizes 1 64 1024 4096] [--budget 300] [--oracle-worlds 32]
"""

from __future__ import annotations

import argparse
import json
import os
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

SHORT_STEPS = 10  # control steps of the short run
CLOSED_LOOP = ("mjwarp", "newton", "warp")


def _log(record: dict) -> None:
    """One machine-readable line per measurement."""
    print(json.dumps(record), flush=True)


def _toss(steps: int | None = None):
    from tt.sim.motions import for_space, get_motion
    from tt.sim.motions.base import Motion

    toss = for_space([get_motion("toss")], "viperx")[0]
    if steps is None or steps >= toss.steps:
        return toss
    return Motion(f"toss[:{steps}]", toss.pos[:steps], toss.quat[:steps])


def _one_per_topology(designs):
    from tt.kernels.model import topology_key
    from tt.sim.designs import get_space

    space = get_space("viperx")
    seen = {}
    for d in designs:
        seen.setdefault(topology_key(space.model(d), space.ee_sites()), d)
    return list(seen.values())


def _closed_loop(backend: str, designs, steps: int) -> float:
    """Wall seconds of one closed-loop rollout of `designs` on the first `steps` of the toss."""
    from tt.sim.rollout import rollout

    motion = _toss(steps)
    start = time.perf_counter()
    rollout(designs, [motion], backend=backend, device="cpu")
    return time.perf_counter() - start


# --------------------------------------------------------------------------- compile probe


def _probe(backend: str, cache: str) -> None:
    """Child process: first and warm call with an empty kernel cache; prints one JSON line."""
    import warp as wp

    wp.config.kernel_cache_dir = cache
    wp.config.quiet = True
    from tt.sim.designs import get_space

    designs = _one_per_topology(get_space("viperx").sample(64, seed=0))
    first = _closed_loop(backend, designs, SHORT_STEPS)
    warm = _closed_loop(backend, designs, SHORT_STEPS)
    print(json.dumps({"probe": backend, "first_s": first, "warm_s": warm, "designs": len(designs)}), flush=True)


def _compile_times(backends) -> dict:
    out = {}
    for backend in backends:
        with tempfile.TemporaryDirectory(prefix=f"tt_warp_cache_{backend}_") as cache:
            proc = subprocess.run(
                [sys.executable, __file__, "--probe", backend, "--cache", cache], capture_output=True, text=True, check=False
            )
        lines = [line for line in proc.stdout.splitlines() if line.startswith('{"probe"')]
        if proc.returncode != 0 or not lines:
            raise RuntimeError(f"compile probe for {backend} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
        out[backend] = json.loads(lines[-1])
        _log(out[backend])
    return out


# --------------------------------------------------------------------------- measurements


def _oracle(designs) -> dict:
    from tt.sim.validate import oracle_rollout

    motion = _toss()
    start = time.perf_counter()
    ep = oracle_rollout(designs, [motion])
    seconds = time.perf_counter() - start
    alive = ep.alive.numpy()
    # Executed control steps: the alive ones, plus the step that terminated a world early.
    executed = int(alive.sum() + np.sum(alive.sum(axis=1) < motion.steps))
    world_steps = executed * 10
    rec = {"backend": "oracle", "worlds": len(designs), "world_steps": world_steps, "seconds": seconds,
           "rate": world_steps / seconds}  # fmt: skip
    _log(rec)
    return rec


def _mujoco_rollout(designs, physics_steps: int, threads: int = 2, chunk: int = 256) -> dict:
    """MuJoCo C's threaded rollout: physics only, open loop; one call per structure group
    and chunk of worlds (bounds the state output's memory)."""
    import mujoco
    from mujoco import rollout as mj_rollout

    from tt.sim.designs import get_space
    from tt.sim.mjwarp_backend import structure_key

    space = get_space("viperx")
    models = [space.model(d) for d in designs]
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
    world_steps = len(designs) * physics_steps
    rec = {"backend": "mujoco.rollout", "worlds": len(designs), "world_steps": world_steps, "seconds": seconds,
           "rate": world_steps / seconds}  # fmt: skip
    _log(rec)
    return rec


def _predict(points: list[tuple[int, float]], n: int) -> float:
    """A quantity at size n from its values at the last one or two sizes: the line through
    two points (at least the last value), proportional to N through one."""
    if len(points) == 1:
        n0, v0 = points[0]
        return v0 * n / n0
    (n0, v0), (n1, v1) = points[-2:]
    return max(v1, v1 + (v1 - v0) / (n1 - n0) * (n - n1))


def _closed_loop_rate(backend: str, designs, full_steps: int, budget: float, history: list[dict]) -> dict:
    """Stepping rate and setup time of one closed-loop combination, within about `budget`
    seconds; `history` holds this backend's records at smaller sizes."""
    n = len(designs)
    rec = {"backend": backend, "worlds": n}
    step_est = None  # seconds per control step
    if history:
        setup_est = _predict([(h["worlds"], h["setup_s"]) for h in history], n)
        step_est = _predict([(h["worlds"], h["worlds"] * 10 / h["rate"]) for h in history], n)
        if setup_est + SHORT_STEPS * step_est > budget:
            rec["skipped"] = (
                f"predicted {setup_est / 60:.0f} min of setup and {step_est:.0f} s per control step "
                f"(from N = {', '.join(str(h['worlds']) for h in history[-2:])}), over the {budget:.0f} s budget"
            )
            _log(rec)
            return rec
    short = _closed_loop(backend, designs, SHORT_STEPS)
    per_step = short / SHORT_STEPS  # an upper bound: includes setup
    if step_est is not None:
        per_step = min(per_step, step_est)
    long_steps = full_steps
    if short + long_steps * per_step > budget:
        long_steps = min(full_steps, int(max(3 * SHORT_STEPS, (budget - short) / per_step)))
    long = _closed_loop(backend, designs, long_steps)
    if long < 2.0:
        # Fast combinations: the best of 5 of each run, so timer noise and other jobs'
        # bursts do not decide a difference of milliseconds.
        short = min([short] + [_closed_loop(backend, designs, SHORT_STEPS) for _ in range(4)])
        long = min([long] + [_closed_loop(backend, designs, long_steps) for _ in range(4)])
    world_steps = n * 10 * (long_steps - SHORT_STEPS)
    rate = world_steps / max(long - short, 1e-9)
    rec.update(
        rate=rate,
        setup_s=max(short - n * 10 * SHORT_STEPS / rate, 0.0),
        control_steps=long_steps,
        truncated=long_steps < full_steps,
        seconds_short=short,
        seconds_long=long,
    )
    _log(rec)
    return rec


# --------------------------------------------------------------------------- report


def _fmt_rate(rate: float) -> str:
    if rate >= 1e6:
        return f"{rate / 1e6:.2f} M"
    if rate >= 1e3:
        return f"{rate / 1e3:.1f} k"
    return f"{rate:.0f}"


def _report(args, results, compile_times, oracle, load_before, load_after, wall) -> str:
    sizes = args.sizes
    full = _toss().steps
    header = ["backend"] + [f"N = {n}" for n in sizes]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    notes = []
    rates: dict[tuple[str, int], float] = {}
    lines.append("| oracle (MuJoCo C + mink, 1 world at a time) | " + " | ".join(
        [_fmt_rate(oracle["rate"]) + (" (measured)" if n == min(sizes) else "") for n in sizes]) + " |")  # fmt: skip
    for n in sizes:
        rates[("oracle", n)] = oracle["rate"]
    row = ["mujoco.rollout (C, 2 threads, open loop)"]
    for n in sizes:
        rec = results["mujoco.rollout"][n]
        rates[("mujoco.rollout", n)] = rec["rate"]
        row.append(_fmt_rate(rec["rate"]))
    lines.append("| " + " | ".join(row) + " |")
    for backend in CLOSED_LOOP:
        row = [f"{backend} (closed loop)"]
        for n in sizes:
            rec = results[backend].get(n)
            if rec is None or "rate" not in rec:
                row.append("skipped")
                if rec is not None:
                    notes.append(f"- {backend}, N = {n}: skipped: {rec['skipped']}.")
                continue
            rates[(backend, n)] = rec["rate"]
            cell = _fmt_rate(rec["rate"])
            if rec["truncated"]:
                cell += " *"
                notes.append(f"- {backend}, N = {n}: * toss truncated to its first {rec['control_steps']} of {full} control steps.")
            row.append(cell)
        lines.append("| " + " | ".join(row) + " |")
    table = "\n".join(lines)

    ratio_lines = ["| backend | " + " | ".join(f"N = {n}" for n in sizes) + " |", "|" + "---|" * (len(sizes) + 1)]
    for backend in ("mujoco.rollout", *CLOSED_LOOP):
        cells = []
        for n in sizes:
            r = rates.get((backend, n))
            c = rates.get(("mujoco.rollout", n))
            cells.append("-" if r is None else f"{r / oracle['rate']:.3g}x / {r / c:.2g}x")
        ratio_lines.append(f"| {backend} | " + " | ".join(cells) + " |")
    ratios = "\n".join(ratio_lines)

    setup_lines = ["| backend | " + " | ".join(f"N = {n}" for n in sizes) + " | first call (s) | warm call (s) | compile (s) |",
                   "|" + "---|" * (len(sizes) + 4)]  # fmt: skip
    for backend in CLOSED_LOOP:
        cells = []
        for n in sizes:
            rec = results[backend].get(n)
            cells.append("-" if rec is None or "rate" not in rec else f"{rec['setup_s']:.1f}")
        ct = compile_times.get(backend)
        extra = ["-", "-", "-"] if ct is None else [f"{ct['first_s']:.1f}", f"{ct['warm_s']:.1f}", f"{ct['first_s'] - ct['warm_s']:.0f}"]
        setup_lines.append(f"| {backend} | " + " | ".join(cells + extra) + " |")
    setup = "\n".join(setup_lines)

    text = (
        "# Rollout speed: world-steps per second\n\n"
        + machine_header("cpu")
        + f"- load average (1, 5, 15 min): {load_before[0]:.1f}, {load_before[1]:.1f}, {load_before[2]:.1f} at the start, "
        f"{load_after[0]:.1f}, {load_after[1]:.1f}, {load_after[2]:.1f} at the end: the machine was shared with other "
        f"jobs, so every rate is a lower bound; {wall / 60:.0f} min wall in all\n"
        f"- workload: N random ViperX designs (seed 0, nested: N = 64 is the first 64 of the 4096) x the toss "
        f"({full} control steps at 50 Hz, 10 physics steps of 0.002 s each); a world-step is one physics step of one world\n"
        f"- Warp device: cpu (no GPU here)\n\n"
        "## World-steps per second\n\n" + table + "\n\n"
        + ("\n".join(notes) + "\n\n" if notes else "")
        + f"The oracle row was measured on {oracle['worlds']} worlds ({oracle['world_steps']} executed world-steps in "
        f"{oracle['seconds']:.1f} s) and holds at every N: it runs one world after another. mujoco.rollout runs "
        "physics only (no controller, no records); mjwarp, newton and warp run the oracle's controller at 50 Hz and "
        "record Episodes. Closed-loop rates exclude setup (next table).\n\n"
        "On the CPU, mjwarp and newton are bound by Python's cost of launching Warp kernels, not by arithmetic: "
        "`mjw.step` launches about 80 kernels per physics step and Featherstone about 15, and ViperX designs come in "
        "3 topologies, which mjwarp runs as 3 batched models one after another (newton holds every world in one "
        "model; tt's IK runs once per topology in both). At small N that overhead is all there is, so their rates "
        "grow with N; tt's warp backend runs a whole chunk of control steps of a world in one thread of one launch. "
        "On a GPU these launch counts are what CUDA graphs remove; this table says nothing about GPU speed.\n\n"
        "## Speed-up: vs the oracle / vs mujoco.rollout (2 threads)\n\n" + ratios + "\n\n"
        "## Setup and compile time\n\n"
        "Setup [s] per N (model building and start posture; newton imports one MJCF per design), then the compile "
        "probe: a fresh process with an empty Warp kernel cache runs 3 designs (one per ViperX topology) x 10 control "
        "steps twice; compile = first call - warm call.\n\n" + setup + "\n\n"
        "MuJoCo-Warp 3.17 returns all-zero gradients under `wp.Tape` (it is not differentiable through `mjw.step`); "
        "Newton's Featherstone and tt's warp kernels differentiate (tests/test_backends.py, "
        "tests/test_kernels_rollout.py).\n"
    )
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 1024, 4096])
    ap.add_argument("--budget", type=float, default=300.0, help="seconds allowed per closed-loop combination")
    ap.add_argument("--oracle-worlds", type=int, default=32)
    ap.add_argument("--backends", nargs="+", default=list(CLOSED_LOOP))
    ap.add_argument("--no-compile-probe", action="store_true")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "sim.md")
    ap.add_argument("--probe", help=argparse.SUPPRESS)
    ap.add_argument("--cache", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.probe:
        _probe(args.probe, args.cache)
        return
    args.sizes = sorted(args.sizes)

    import warp as wp

    wp.config.quiet = True
    from tt.sim.designs import get_space

    load_before = os.getloadavg()
    begin = time.perf_counter()
    compile_times = {} if args.no_compile_probe else _compile_times(args.backends)

    designs = get_space("viperx").sample(max(args.sizes), seed=0)
    full = _toss().steps
    # Load every module once in this process (from the warm cache), so no timing below compiles.
    warmup = _one_per_topology(designs)
    for backend in args.backends:
        _closed_loop(backend, warmup, 2)

    oracle = _oracle(designs[: args.oracle_worlds])
    results: dict[str, dict[int, dict]] = {"mujoco.rollout": {}, **{b: {} for b in CLOSED_LOOP}}
    history: dict[str, list[dict]] = {b: [] for b in args.backends}
    for n in args.sizes:
        results["mujoco.rollout"][n] = _mujoco_rollout(designs[:n], full * 10)
        for backend in args.backends:
            rec = _closed_loop_rate(backend, designs[:n], full, args.budget, history[backend])
            results[backend][n] = rec
            if "rate" in rec:
                history[backend].append(rec)
    text = _report(args, results, compile_times, oracle, load_before, os.getloadavg(), time.perf_counter() - begin)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
