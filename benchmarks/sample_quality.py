"""Do the generator's samples beat uniform draws? Sample quality before any ranking (issue 51).

For each (seed, validation motion) this draws n designs three ways, and validates every one
on the oracle (MuJoCo C + mink):

* ``uniform``: n designs drawn uniformly from the space (what Random screens);
* one row per checkpoint: n samples of its motion-to-robot task for the motion (20 DDIM steps,
  evenly placed query steps), each decoded to the nearest design of the space.

It reports, per source, the validated reward's median and quartiles, the share of episodes
that track the whole motion (survival 1) and the median position error, pooled over every
(seed, motion) and per motion. The targets (issue 51): a generator's median at or above the
75th percentile of uniform designs on the same motions, and a tracking share at least 20
points above uniform's.

The same pools give the test-time comparisons at equal rollouts, each pick validated on the
oracle, for n in ``--ns`` (the first n draws of each pool):

* ``Random(n)``: the uniform pool's best by the batched simulator (the space's default backend:
  ``warp``, or ``mjbatch`` for the quadruped);
* ``zeroth-sim(n)``: a checkpoint's pool, best by the same simulator;
* ``Zeroth-Order(n)``: a checkpoint's pool, best by the shipped dynamics critic's prediction
  (`tt.guidance.predicted.predict_designs`, no rollout).

* ``CMA-ES(n)``: tt's batched CMA-ES (`tt.baselines.CMAES`, default config) with a budget of n
  rollouts, for n of ``--ns`` at or above one restart (popsize x generations); its best validated.

Paired differences against Random(n) are given with 95 % CIs (`tt.report.mean_ci`) over every
(seed, motion). ``--validate picks`` validates only the designs the searches pick (what the
best-of-n table needs) instead of every draw, for runs over many (seed, motion) pairs; the
pooled distributions are then left out.

Usage: ``python benchmarks/sample_quality.py CKPT [CKPT ...] [--seeds 9] [--motions 9] [--n 64]
[--ns 1 4 16 64] [--steps 20] [--reward tracking] [--validate all|picks]
[--out benchmarks/results/sample_quality.md]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from machine import load_line, machine_header, write_report  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def motions_for(space: str, count: int) -> list:
    """`count` validation motions, one per skill first (variant 100 of each), then the others."""
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, motion_set

    val = for_space(motion_set("val", arms=get_space(space).ee_count), space)
    order = [m for v in range(3) for m in val[v::3]]
    return order[:count]


def model_pool(trained, decoder, motion, reward_cfg, n: int, seed: int, steps: int, temperature: float = 1.0) -> list:
    """n decoded samples of `trained`'s motion-to-robot task for `motion` (sampling order), from
    starting noise scaled by `temperature`."""
    from tt.guidance.zeroth import CandidateSampler, embodiment_batch

    gen = CandidateSampler(trained, "cpu").run(
        (motion,), reward_cfg, n, seed=seed, num_steps=steps, critic="joint", temperature=temperature
    )
    batch = embodiment_batch(trained.layout, trained.normalizer, gen.tokens)
    return [decoder(batch, i).design for i in range(n)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="*", help="generators to compare (checkpoint files)")
    p.add_argument("--seeds", type=int, default=9)
    p.add_argument("--motions", type=int, default=9, help="validation motions per seed (one per skill first)")
    p.add_argument(
        "--paired", action="store_true", help="seed i runs motion i only (codesign.py's single-trajectory runs)"
    )
    p.add_argument("--n", type=int, default=64, help="designs per source, seed and motion")
    p.add_argument("--ns", type=int, nargs="+", default=[1, 4, 16, 64], help="budgets of the best-of-n comparisons")
    p.add_argument("--steps", type=int, default=20, help="DDIM steps of each sample")
    p.add_argument(
        "--temperatures",
        type=float,
        nargs="+",
        default=[1.0],
        help="scales of the starting noise; each checkpoint is one source per temperature",
    )
    p.add_argument("--reward", default="tracking")
    p.add_argument("--critic", default=None, help="dynamics critic of the Zeroth-Order rows (default: the shipped one)")
    p.add_argument("--out", default=str(RESULTS / "sample_quality.md"))
    p.add_argument(
        "--validate",
        choices=("all", "picks"),
        default="all",
        help="validate every draw on the oracle, or only the designs the searches pick",
    )
    p.add_argument("--records", default=None, help="also write every validated draw to this JSON file")
    p.add_argument(
        "--from-records",
        nargs="+",
        default=None,
        help="rewrite the report (and plot) from --records files (several: runs of the same seeds, motions and "
        "pools merged, each checkpoint a source); no run",
    )
    args = p.parse_args()
    if args.from_records is not None:
        write_outputs(merge_records([json.loads(Path(f).read_text()) for f in args.from_records]), Path(args.out))
        return
    if not args.checkpoints:
        p.error("give the checkpoints to compare (or --from-records)")
    if args.n < max(args.ns) or min(args.ns) < 1:
        p.error("--ns must lie in 1 .. --n")

    from tt.baselines import CMAES, CMAESConfig, Problem, evaluate_designs
    from tt.dit.checkpoint import default_checkpoint, load_model
    from tt.guidance.predicted import predict_designs
    from tt.guidance.zeroth import DesignDecoder
    from tt.sim.designs import get_space
    from tt.sim.rewards import get_reward

    loaded = [(Path(c).name, load_model(c, device="cpu")) for c in args.checkpoints]
    models = [
        (name if t == 1.0 else f"{name} T={t:g}", trained, t) for name, trained in loaded for t in args.temperatures
    ]
    space = loaded[0][1].space
    sp = get_space(space)
    critic_path = args.critic or default_checkpoint(space, task="dynamics")
    critic = load_model(critic_path, device="cpu")
    reward_cfg = get_reward(args.reward, space)
    decoder = DesignDecoder(sp)
    motions = motions_for(space, args.motions)
    load_start, start = load_line(), time.perf_counter()
    records = []
    pairs = [(seed, mi) for seed in range(args.seeds) for mi in range(len(motions))]
    if args.paired:
        pairs = [(seed, seed % len(motions)) for seed in range(args.seeds)]
    for seed, mi in pairs:
        motion = motions[mi]
        t0 = time.perf_counter()
        t = time.perf_counter()
        pools = {"uniform": sp.sample(args.n, seed=10_000 * seed + mi)}
        draw_s = {"uniform": time.perf_counter() - t}
        for name, trained, temperature in models:
            t = time.perf_counter()
            pools[name] = model_pool(
                trained, decoder, motion, reward_cfg, args.n, 10_000 * seed + mi, args.steps, temperature
            )
            draw_s[name] = time.perf_counter() - t
        rec = {"seed": seed, "motion": motion.name}
        for name, designs in pools.items():
            t = time.perf_counter()
            sim = evaluate_designs(designs, (motion,), args.reward, threads=1)  # the space's default backend
            sim_s = time.perf_counter() - t
            row = {"sim_reward": sim.reward[:, 0].tolist(), "draw_seconds": draw_s[name], "sim_seconds": sim_s}
            if name != "uniform":
                t = time.perf_counter()
                pred = predict_designs(critic, designs, (motion,), reward_cfg, num_steps=args.steps, seed=seed)
                row["predicted"] = np.where(np.isfinite(pred.reward[:, 0]), pred.reward[:, 0], -np.inf).tolist()
                row["critic_seconds"] = time.perf_counter() - t
            keys = ("sim_reward",) if name == "uniform" else ("sim_reward", "predicted")
            todo = (
                range(len(designs))
                if args.validate == "all"
                else sorted({_argmax(row[k], n) for k in keys for n in args.ns})
            )
            oracle = evaluate_designs([designs[i] for i in todo], (motion,), args.reward, backend="mujoco")
            for key, metric in (("reward", None), ("pos_err", "pos_err"), ("survival", "survival")):
                vals = oracle.reward[:, 0] if metric is None else np.asarray(oracle.metrics[metric])[:, 0]
                full = np.full(len(designs), np.nan)
                full[list(todo)] = vals
                row[key] = full.tolist()
            rec[name] = row
        rec["cmaes"] = {}
        for n in args.ns:
            if n < CMAESConfig().popsize * CMAESConfig().generations:
                continue
            problem = Problem(space, (motion,), args.reward, budget=n, seed=10_000 * seed + mi, threads=1)
            res = CMAES().optimize(problem)
            val = evaluate_designs([res.best], (motion,), args.reward, backend="mujoco")
            rec["cmaes"][str(n)] = {"reward": float(val.reward[0, 0]), "seconds": res.seconds}
        records.append(rec)
        summary = {k: round(float(np.nanmedian(rec[k]["sim_reward"])), 1) for k in pools}
        print(
            json.dumps(
                {
                    "seed": seed,
                    "motion": motion.name,
                    "median_simulated_reward": summary,
                    "seconds": round(time.perf_counter() - t0, 1),
                }
            ),
            flush=True,
        )
    saved = {
        "args": vars(args),
        "records": records,
        "minutes": (time.perf_counter() - start) / 60,
        "load_start": load_start,
        "load_end": load_line(),
        "header": machine_header("cpu").rstrip(),
        "critic": str(critic_path),
    }
    if args.records is not None:
        Path(args.records).write_text(json.dumps(saved))
    write_outputs(saved, Path(args.out))


def merge_records(runs: list[dict]) -> dict:
    """One record of several runs over the same (seed, motion) pairs and settings: the union of
    their sources. The uniform pools and CMA-ES runs depend only on (seed, motion), so they must
    agree; each run's command is kept for the report."""
    if len(runs) == 1:
        return runs[0]
    first = runs[0]
    same = ("seeds", "motions", "paired", "n", "ns", "steps", "reward", "validate")
    for other in runs[1:]:
        diff = [k for k in same if first["args"].get(k) != other["args"].get(k)]
        keys = [(r["seed"], r["motion"]) for r in first["records"]]
        if diff or keys != [(r["seed"], r["motion"]) for r in other["records"]]:
            raise SystemExit(f"--from-records: runs differ in {diff or 'their (seed, motion) pairs'}")
        for a, b in zip(first["records"], other["records"]):
            if a["uniform"]["reward"] != b["uniform"]["reward"]:
                raise SystemExit("--from-records: the runs' uniform pools differ")
    records = [dict(r) for r in first["records"]]
    for other in runs[1:]:
        for rec, extra in zip(records, other["records"]):
            rec.update({k: v for k, v in extra.items() if k not in rec})
    args = dict(first["args"])
    args["checkpoints"] = [c for r in runs for c in r["args"]["checkpoints"]]
    args["temperatures"] = sorted({t for r in runs for t in r["args"].get("temperatures", [1.0])}, reverse=True)
    return {
        **first,
        "args": args,
        "records": records,
        "minutes": sum(r["minutes"] for r in runs),
        "load_end": runs[-1]["load_end"],
        "commands": [command_line(argparse.Namespace(**{"validate": "all", **r["args"]})) for r in runs],
    }


def command_line(args) -> str:
    """The command that ran (or would rerun) a run with `args`."""
    temps = list(getattr(args, "temperatures", [1.0]))
    return (
        f"python benchmarks/sample_quality.py {' '.join(args.checkpoints)} --seeds {args.seeds} "
        f"--motions {args.motions}{' --paired' if args.paired else ''} --n {args.n} --ns "
        f"{' '.join(map(str, args.ns))} --steps {args.steps}"
        f"{' --validate picks' if args.validate == 'picks' else ''}"
        f"{'' if temps == [1.0] else ' --temperatures ' + ' '.join(f'{t:g}' for t in temps)}"
    )


def write_outputs(saved: dict, out: Path) -> None:
    """The report and its plot from a run's record (what ``--records`` writes)."""
    records = saved["records"]
    args = argparse.Namespace(**{"validate": "all", **saved["args"]})
    names = [k for k in records[0] if k not in ("seed", "motion", "uniform", "cmaes")]
    out.parent.mkdir(parents=True, exist_ok=True)
    write_report(out, report(records, names, args, saved))
    plot(records, names, args.ns, args.n, out.with_suffix(".png"))


def plot(records: list, names: list[str], ns: list[int], n_pool: int, path: Path) -> None:
    """Validated reward of the best of n against n and against wall time (the pool's per-design costs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    curves = [("Random", "uniform", "sim_reward", ("sim_seconds",))]
    for s in names:
        curves += [
            (f"zeroth-sim {s}", s, "sim_reward", ("draw_seconds", "sim_seconds")),
            (f"Zeroth-Order {s}", s, "predicted", ("draw_seconds", "critic_seconds")),
        ]
    for label, src, key, costs in curves:
        mean = [np.mean([_pick(rec[src], key, n) for rec in records]) for n in ns]
        per = np.mean([sum(rec[src].get(c, 0.0) for c in costs) for rec in records]) / n_pool
        style = "-o" if src == "uniform" else ("--s" if key == "predicted" else "-^")
        axes[0].plot(ns, mean, style, label=label)
        axes[1].plot([per * n for n in ns], mean, style, label=label)
    runs = sorted({int(n) for rec in records for n in rec.get("cmaes", {})})
    if runs:
        mean = [np.mean([rec["cmaes"][str(n)]["reward"] for rec in records]) for n in runs]
        secs = [np.mean([rec["cmaes"][str(n)]["seconds"] for rec in records]) for n in runs]
        axes[0].plot(runs, mean, "-D", label="CMA-ES")
        axes[1].plot(secs, mean, "-D", label="CMA-ES")
    axes[0].set(
        xscale="log",
        xlabel="n (designs drawn)",
        ylabel="validated reward (mean over runs)",
        title="best of n at equal draws",
    )
    axes[1].set(xscale="log", xlabel="wall time [s] (pool cost per design x n)", title="at equal wall time")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _argmax(score: list, n: int) -> int:
    """The index of the first n scores' best (first on ties; NaN never wins)."""
    s = np.asarray(score[:n], float)
    return int(np.argmax(np.where(np.isnan(s), -np.inf, s)))


def _pick(row: dict, key: str, n: int) -> float:
    """The validated reward of the first n designs' best by `key`."""
    return float(row["reward"][_argmax(row[key], n)])


def report(records: list, names: list[str], args, saved: dict) -> list[str]:
    """The report's lines: `records` of the sources `names` (and "uniform"), the run's `args`
    and the rest of its record `saved` (machine header, loads, minutes, critic)."""
    motions = list(dict.fromkeys(rec["motion"] for rec in records))
    lines = [
        "# Sample quality: generator samples against uniform designs (issue 51)"
        if args.validate == "all"
        else "# Test-time scaling: the best of n draws at equal rollouts (issue 51)",
        "",
        saved["header"],
        f"- load (1, 5, 15 min) at start: {saved['load_start']}; at end: {saved['load_end']}",
        f"- {args.seeds} seeds x {len(motions)} validation motions ({', '.join(motions)})"
        f"{' (seed i on motion i only)' if args.paired else ''}, "
        f"{args.n} designs per source each, reward `{args.reward}`, {args.steps} DDIM steps, "
        f"{'every design' if args.validate == 'all' else 'every design a search picks'} validated on the oracle "
        f"(MuJoCo C + mink); {saved['minutes']:.1f} min in all",
        *(f"- command: `{c}`" for c in saved.get("commands", [command_line(args)])),
        "",
    ]
    if args.validate == "all":
        lines += distribution_lines(records, names)
    lines += best_of_n_lines(records, names, args, saved)
    return lines


def distribution_lines(records: list, names: list[str]) -> list[str]:
    """The pooled and per-motion distributions of every validated draw."""
    sources = ["uniform", *names]
    lines = [
        "## Validated reward of the draws, pooled over every seed and motion",
        "",
        "| source | designs | reward p25 | median | p75 | tracks the whole motion | median position error [cm] |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    pooled = {}
    for s in sources:
        r = np.concatenate([rec[s]["reward"] for rec in records])
        surv = np.concatenate([rec[s]["survival"] for rec in records])
        pe = np.concatenate([rec[s]["pos_err"] for rec in records])
        pooled[s] = (r, surv)
        q = np.percentile(r, [25, 50, 75])
        lines.append(
            f"| {s} | {len(r)} | {q[0]:.1f} | {q[1]:.1f} | {q[2]:.1f} | {100 * np.mean(surv >= 1.0):.1f} % | "
            f"{np.nanmedian(pe):.2f} |"
        )
    u75 = np.percentile(pooled["uniform"][0], 75)
    u_share = 100 * np.mean(pooled["uniform"][1] >= 1.0)
    lines += [
        "",
        f"Targets: median at or above uniform's 75th percentile ({u75:.1f}); tracking share at least "
        f"{u_share + 20:.1f} % (uniform's + 20 points).",
        "",
    ]
    for s in names:
        med = np.median(pooled[s][0])
        share = 100 * np.mean(pooled[s][1] >= 1.0)
        lines.append(
            f"- `{s}`: median {med:.1f} ({'meets' if med >= u75 else 'misses'} the first), tracking "
            f"{share:.1f} % ({'meets' if share >= u_share + 20 else 'misses'} the second)"
        )
    lines += [
        "",
        "## Per motion: median validated reward (share tracking the whole motion)",
        "",
        "| motion | " + " | ".join(sources) + " |",
        "|---|" + "---:|" * len(sources),
    ]
    for m in dict.fromkeys(rec["motion"] for rec in records):
        recs = [rec for rec in records if rec["motion"] == m]
        cells = []
        for s in sources:
            r = np.concatenate([rec[s]["reward"] for rec in recs])
            surv = np.concatenate([rec[s]["survival"] for rec in recs])
            cells.append(f"{np.median(r):.1f} ({100 * np.mean(surv >= 1):.0f} %)")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines + [""]


def best_of_n_lines(records: list, names: list[str], args, saved: dict) -> list[str]:
    """The best-of-n table against Random(n) and the wall times."""
    from tt.report import mean_ci

    sources = ["uniform", *names]
    lines = [
        "## Best of n at equal rollouts, validated on the oracle",
        "",
        "Random(n) and zeroth-sim(n) pick the simulator's best of the first n draws of their pool; Zeroth-Order(n) "
        f"picks by the critic `{Path(saved['critic']).name}` without a rollout. Mean validated reward over "
        f"{len(records)} (seed, motion) pairs; the paired difference against Random(n) with its 95 % CI.",
        "",
        "| n | method | validated reward | minus Random(n) | higher / lower |",
        "|---:|---|---:|---:|---:|",
    ]
    for n in args.ns:
        base = np.array([_pick(rec["uniform"], "sim_reward", n) for rec in records])
        m, h = mean_ci(base)
        lines.append(f"| {n} | Random | {m:.1f} ± {h:.1f} | | |")
        if all(str(n) in rec.get("cmaes", {}) for rec in records):
            v = np.array([rec["cmaes"][str(n)]["reward"] for rec in records])
            m, h = mean_ci(v)
            dm, dh = mean_ci(v - base)
            lines.append(
                f"| {n} | CMA-ES | {m:.1f} ± {h:.1f} | {dm:+.1f} ± {dh:.1f} | "
                f"{int(np.sum(v > base))} / {int(np.sum(v < base))} |"
            )
        for s in names:
            for label, key in (("zeroth-sim", "sim_reward"), ("Zeroth-Order", "predicted")):
                v = np.array([_pick(rec[s], key, n) for rec in records])
                m, h = mean_ci(v)
                dm, dh = mean_ci(v - base)
                lines.append(
                    f"| {n} | {label} `{s}` | {m:.1f} ± {h:.1f} | {dm:+.1f} ± {dh:.1f} | "
                    f"{int(np.sum(v > base))} / {int(np.sum(v < base))} |"
                )
    lines += [
        "",
        "## Wall time of one (seed, motion) at n = " + f"{args.n}",
        "",
        "Mean seconds on this machine (one thread for the rollout, torch on every core): drawing the pool "
        "(uniform: sampling the space; a checkpoint: DDIM sampling and decoding every sample), its batched "
        "simulation (what Random and zeroth-sim add), and the critic's predictions (what Zeroth-Order adds). "
        "At equal wall time Random screens far more designs than a learned method samples.",
        "",
        "| source | draw (s) | simulate (s) | critic (s) |",
        "|---|---:|---:|---:|",
    ]
    for s in sources:
        draw = np.mean([rec[s]["draw_seconds"] for rec in records])
        sim = np.mean([rec[s]["sim_seconds"] for rec in records])
        crit = np.mean([rec[s].get("critic_seconds", np.nan) for rec in records])
        lines.append(f"| {s} | {draw:.2f} | {sim:.2f} | {'-' if np.isnan(crit) else f'{crit:.2f}'} |")
    runs = sorted({int(n) for rec in records for n in rec.get("cmaes", {})})
    if runs:
        lines += [
            "",
            "CMA-ES, seconds per run (batched, one thread, compile excluded): "
            + ", ".join(f"n = {n}: {np.mean([rec['cmaes'][str(n)]['seconds'] for rec in records]):.2f}" for n in runs),
        ]
    return lines


if __name__ == "__main__":
    main()
