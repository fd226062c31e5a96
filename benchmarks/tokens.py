"""RoboToken throughput and sizes on this machine.

* Tokenization: robots per second on a batch of compiled models (``--robots`` designs per
  space; compiling the MJCF is not timed: the tokenizer's input is an `MjModel`). "cold":
  ``tokenize_models`` (plans of every topology derived in the call); "warm": a `Tokenizer`
  that has seen the space's topologies before, as in a data-generation loop. Reference
  beside them: the same warm `Tokenizer` called once per robot (``--single`` robots), the
  unbatched cost.
* Episode tokens: episode-samples per second of ``episode_tokens`` (8 random steps per
  world) on a synthetic episode of ``--worlds`` worlds x ``--steps`` control steps whose
  worlds run the tokenized designs (values do not change the cost). Reference beside it:
  one world per call (``--single`` worlds, each with only its own robot), the unbatched
  cost.
* Detokenization: robots per second of ``detokenize`` (MJCF text + MuJoCo compile).
* Sizes: RoboTokens per robot next to the MJCF text length (characters) of each space.

Each timing is the best of ``--repeats`` runs, wall clock and process CPU time (the CPU
time is less disturbed by other jobs on a shared machine). Prints one JSON line per
measurement (``{"bench": "tokens", ...}``) and writes ``benchmarks/results/tokens.md``.
Torch runs with ``--threads`` intra-op threads (default 1: data generation runs one
worker process per core). Usage: ``python benchmarks/tokens.py [--robots 1000] [--worlds 4096]``.
"""

from __future__ import annotations

import os

# One thread per library (OpenMP, BLAS), as torch gets with --threads 1: on a shared 2-core
# machine idle-spinning worker threads otherwise burn CPU time that the rates would count.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import warnings
from pathlib import Path

import numpy as np
import torch

try:
    from machine import machine_header
except ImportError:  # imported as benchmarks.tokens
    from benchmarks.machine import machine_header

from tt.sim.designs import SPACE_NAMES, get_space
from tt.sim.episode import Episode
from tt.tokens import SCHEMA_VERSION, Tokenizer, TokenizeWarning, detokenize, episode_tokens, tokenize_models
from tt.tokens.schema import EMBODIMENT_TYPES

RESULTS = Path(__file__).parent / "results" / "tokens.md"


def _best(fn, repeats: int) -> tuple[float, float]:
    """Best wall and CPU seconds of `fn()` over `repeats` runs."""
    wall, cpu = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu)


def _synthetic_episode(index, worlds: int, steps: int, seed: int) -> Episode:
    """An Episode of the right shapes for robots `index` (random values)."""
    g = torch.Generator().manual_seed(seed)
    nq = max(int(r.dyna_qposadr.max(initial=0)) + 1 for r in index) + 7
    nu = max(len(r.actuator_mj) for r in index)
    a = len(index[0].track_link)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    quat = torch.nn.functional.normalize(torch.randn(worlds, steps, a, 4, generator=g), dim=-1)
    return Episode(
        qpos=r(worlds, steps, nq),
        qvel=r(worlds, steps, nq),
        ctrl=r(worlds, steps, nu),
        action=r(worlds, steps, nu),
        act_force=r(worlds, steps, nu),
        act_vel=r(worlds, steps, nu),
        ee_pos=r(worlds, steps, a, 3),
        ee_quat=quat,
        target_pos=r(worlds, steps, a, 3),
        target_quat=quat.clone(),
        alive=torch.ones(worlds, steps, dtype=torch.bool),
        fallen=torch.zeros(worlds, steps, dtype=torch.bool),
        design_index=torch.randint(len(index), (worlds,), generator=g),
        motion_index=torch.zeros(worlds, dtype=torch.long),
        dt=0.02,
    )


def _one_world(ep: Episode, w: int) -> Episode:
    """World `w` of `ep` as an Episode of its own (views), running design 0."""
    f = {
        k: getattr(ep, k)[w : w + 1]
        for k in (
            "qpos",
            "qvel",
            "ctrl",
            "action",
            "act_force",
            "act_vel",
            "ee_pos",
            "ee_quat",
            "target_pos",
            "target_quat",
            "alive",
            "fallen",
            "motion_index",
        )
    }
    return Episode(**f, design_index=torch.zeros(1, dtype=torch.long), dt=ep.dt)


def bench_space(name: str, robots: int, worlds: int, steps: int, detok: int, repeats: int, single: int) -> dict:
    space = get_space(name)
    designs = space.sample(robots, seed=0)
    texts = [space.to_mjcf(d) for d in designs]
    import mujoco

    models = [mujoco.MjModel.from_xml_string(t) for t in texts]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TokenizeWarning)
        emb = tokenize_models(models)  # warm-up (imports, allocator)
        wall, cpu = _best(lambda: tokenize_models(models), repeats)
        warm = Tokenizer()
        warm(models)
        wall_w, cpu_w = _best(lambda: warm(models), repeats)
        one = models[: min(single, robots)]
        wall_1, cpu_1 = _best(lambda: [warm([m]) for m in one], 1)
    topologies = len({r.topology for r in emb.index})
    counts = emb.tokens.counts()
    total = emb.tokens.total()
    chars = np.array([len(t) for t in texts])
    out = {
        "space": name,
        "robots": robots,
        "topologies": topologies,
        "tokenize_robots_per_s_wall": robots / wall,
        "tokenize_robots_per_s_cpu": robots / cpu,
        "tokenize_warm_robots_per_s_wall": robots / wall_w,
        "tokenize_warm_robots_per_s_cpu": robots / cpu_w,
        "tokenize_single_robots_per_s_wall": len(one) / wall_1,
        "tokenize_single_robots_per_s_cpu": len(one) / cpu_1,
        "tokens_mean": float(total.mean()),
        "tokens_min": int(total.min()),
        "tokens_max": int(total.max()),
        "mjcf_chars_mean": float(chars.mean()),
        "chars_per_token": float((chars / total).mean()),
        "per_type_max": {t: int(counts[t].max()) for t in EMBODIMENT_TYPES if t in counts},
    }
    ep = _synthetic_episode(emb.index, worlds, steps, seed=1)
    gen = torch.Generator().manual_seed(0)
    episode_tokens(ep, emb.index, steps=8, generator=gen)
    wall, cpu = _best(lambda: episode_tokens(ep, emb.index, steps=8, generator=gen), repeats)
    out["episode_samples_per_s_wall"] = worlds / wall
    out["episode_samples_per_s_cpu"] = worlds / cpu
    per_world = [(_one_world(ep, w), [emb.index[int(ep.design_index[w])]]) for w in range(min(single, worlds))]
    wall, cpu = _best(lambda: [episode_tokens(e, r, steps=8, generator=gen) for e, r in per_world], 1)
    out["episode_single_samples_per_s_wall"] = len(per_world) / wall
    out["episode_single_samples_per_s_cpu"] = len(per_world) / cpu
    sub = emb.tokens.select(np.arange(min(detok, robots)))
    wall, cpu = _best(lambda: detokenize(sub), 1)
    out["detokenize_robots_per_s_wall"] = len(sub) / wall
    out["detokenize_robots_per_s_cpu"] = len(sub) / cpu
    return out


def write_markdown(rows: list[dict], args) -> str:
    lines = [
        "# RoboToken benchmarks",
        "",
        machine_header("cpu").rstrip(),
        f"- RoboToken schema v{SCHEMA_VERSION}",
        f"- load average (1 min) at start, after each space, at end: {args.load_start:.1f}, "
        f"{', '.join(format(r['load_1min'], '.1f') for r in rows)}, {os.getloadavg()[0]:.1f} "
        f"on {os.cpu_count()} cores (other jobs share this machine: wall numbers shrink with load, CPU "
        "numbers less so)",
        f"- torch threads: {args.threads}",
        f"- command: `python benchmarks/tokens.py --robots {args.robots} --worlds {args.worlds} --steps "
        f"{args.steps} --single {args.single} --detok {args.detok} --repeats {args.repeats} --threads "
        f"{args.threads}`",
        "",
        "## Throughput",
        "",
        f"Tokenize: {args.robots} compiled designs per space in one call (MJCF compile not timed); reference: "
        f"one call per robot, {args.single} robots, warm. "
        f"Episodes: {args.worlds} worlds x {args.steps} steps, 8 random steps per world, worlds spread over the "
        f"tokenized designs, in one call; reference: one world per call, {args.single} worlds. "
        f"Detokenize: MJCF text + MuJoCo compile, {args.detok} robots. Best of {args.repeats} "
        "runs; wall clock and process CPU time (the machine may be shared).",
        "",
        "| space | topologies | tokenize robots/s cold (wall / CPU) | warm (wall / CPU) | one robot per call "
        "(wall / CPU) "
        "| episode-samples/s (wall / CPU) | one world per call (wall / CPU) | detokenize robots/s (wall / CPU) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['space']} | {r['topologies']} | {r['tokenize_robots_per_s_wall']:,.0f} / "
            f"{r['tokenize_robots_per_s_cpu']:,.0f} | "
            f"{r['tokenize_warm_robots_per_s_wall']:,.0f} / {r['tokenize_warm_robots_per_s_cpu']:,.0f} | "
            f"{r['tokenize_single_robots_per_s_wall']:,.0f} / {r['tokenize_single_robots_per_s_cpu']:,.0f} | "
            f"{r['episode_samples_per_s_wall']:,.0f} / {r['episode_samples_per_s_cpu']:,.0f} | "
            f"{r['episode_single_samples_per_s_wall']:,.0f} / {r['episode_single_samples_per_s_cpu']:,.0f} | "
            f"{r['detokenize_robots_per_s_wall']:,.0f} / {r['detokenize_robots_per_s_cpu']:,.0f} |"
        )
    lines += [
        "",
        "Targets (issue): >= 2,000 robots/s and >= 20,000 episode-samples/s.",
        "",
        "## Token counts and MJCF size",
        "",
        "Embodiment RoboTokens per robot (joints count two tokens each, one per link they join) next to the "
        "design space's MJCF text in characters.",
        "",
        "| space | RoboTokens mean (min-max) | MJCF characters (mean) | characters per token | most tokens per type |",
        "|---|---:|---:|---:|---|",
    ]
    for r in rows:
        per = ", ".join(f"{k} {v}" for k, v in r["per_type_max"].items())
        lines.append(
            f"| {r['space']} | {r['tokens_mean']:.1f} ({r['tokens_min']}-{r['tokens_max']}) | "
            f"{r['mjcf_chars_mean']:,.0f} | "
            f"{r['chars_per_token']:.0f} | {per} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", type=int, default=1000)
    p.add_argument("--worlds", type=int, default=4096)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--detok", type=int, default=200)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--single", type=int, default=200, help="robots tokenized one per call (the unbatched reference)")
    p.add_argument("--spaces", nargs="*", default=list(SPACE_NAMES))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    args.load_start = os.getloadavg()[0]
    rows = []
    for name in args.spaces:
        r = bench_space(name, args.robots, args.worlds, args.steps, args.detok, args.repeats, args.single)
        r["load_1min"] = os.getloadavg()[0]
        print(json.dumps({"bench": "tokens", **r}), flush=True)
        rows.append(r)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(write_markdown(rows, args))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
