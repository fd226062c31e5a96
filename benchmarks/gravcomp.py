"""Does gravity compensation change which ViperX designs win and how the methods rank? (issue 51, item 6)

The paper's code evaluates its fixed-base arms with MuJoCo's gravity compensation
(``gravcomp="1"`` on every body, `tt.sim.designs.gravcomp`); tt evaluates them without. This
runs the same designs and searches both ways, on the validation motions of
``sample_quality.py`` (one per skill first), tracking reward, every number validated on the
oracle (MuJoCo C + mink) under the setting named:

* uniform designs: ``--designs`` uniform ViperX designs on every motion, validated with and
  without compensation; Spearman's rank correlation of the two rewards per motion and
  pooled, the median reward and the share tracking the whole motion under each, and where
  each setting's best design ranks under the other;
* searches: Random(``--budget``) and CMA-ES(``--budget``) (tt's batched defaults, the warp
  backend) run under each setting, ``--seeds`` seeds x motions; each of the four winners is
  validated under both settings. Reported: each method's validated reward under each
  setting, how often Random's two winners are the same design (the two settings screen the
  same draws), what using the other setting's winner costs (its reward under this setting
  minus this setting's winner's, paired 95 % CI), and the methods' ranking under each
  setting (with the nominal ViperX as a third, search-free row).

Usage: ``python benchmarks/gravcomp.py [--designs 48] [--seeds 3] [--motions 9] [--budget 64]
[--out benchmarks/results/gravcomp.md]``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from machine import load_line, machine_header, write_report  # noqa: E402
from sample_quality import motions_for  # noqa: E402

RESULTS = Path(__file__).parent / "results"
SPACE = "viperx"
SETTINGS = ("plain", "gravcomp")


def _validate(designs, motion, reward: str, space) -> np.ndarray:
    """Oracle rewards of base-space `designs` on `motion`, built in `space` (the base or its
    gravcomp variant), (n,)."""
    from tt.baselines import evaluate_designs

    built = [space.from_base(d) for d in designs] if hasattr(space, "from_base") else list(designs)
    ev = evaluate_designs(built, (motion,), reward, backend="mujoco")
    return ev.reward[:, 0], np.asarray(ev.metrics["survival"])[:, 0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--designs", type=int, default=48, help="uniform designs validated on every motion")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--motions", type=int, default=9, help="validation motions (one per skill first)")
    p.add_argument("--budget", type=int, default=64, help="Random's and CMA-ES's rollouts per motion")
    p.add_argument("--reward", default="tracking")
    p.add_argument("--out", default=str(RESULTS / "gravcomp.md"))
    args = p.parse_args()

    from scipy import stats

    from tt.baselines import CMAES, Problem, RandomSearch
    from tt.sim.designs import get_space

    spaces = {"plain": get_space(SPACE), "gravcomp": get_space(SPACE, gravcomp=True)}
    motions = motions_for(SPACE, args.motions)
    load_start, start = load_line(), time.perf_counter()

    # Uniform designs, validated both ways.
    designs = spaces["plain"].sample(args.designs, seed=0)
    uniform = []
    for motion in motions:
        row = {"motion": motion.name}
        for s in SETTINGS:
            row[s], row[s + "_survival"] = _validate(designs, motion, args.reward, spaces[s])
        uniform.append(row)
        print(f"uniform {motion.name}: rho {stats.spearmanr(row['plain'], row['gravcomp'])[0]:.3f}", flush=True)

    # Nominal ViperX, and the searches under each setting, every winner validated both ways.
    nominal = {s: [] for s in SETTINGS}
    for motion in motions:
        for s in SETTINGS:
            nominal[s].append(float(_validate([spaces["plain"].nominal()], motion, args.reward, spaces[s])[0][0]))
    runs = []
    for seed in range(args.seeds):
        for mi, motion in enumerate(motions):
            run = {"seed": seed, "motion": motion.name, "seconds": {}}
            winners = {}
            for method, optimizer in (("Random", RandomSearch()), ("CMA-ES", CMAES())):
                for s in SETTINGS:
                    problem = Problem(
                        spaces[s].name, (motion,), args.reward, budget=args.budget, seed=10_000 * seed + mi, threads=1
                    )
                    res = optimizer.optimize(problem)
                    best = res.best if s == "plain" else spaces[s].to_base(res.best)
                    winners[(method, s)] = best
                    run["seconds"][f"{method} {s}"] = res.seconds
            keys = list(winners)
            for s in SETTINGS:
                reward, _ = _validate([winners[k] for k in keys], motion, args.reward, spaces[s])
                for k, r in zip(keys, reward):
                    run[f"{k[0]} {k[1]} winner, validated {s}"] = float(r)
            run["random_same"] = winners[("Random", "plain")] == winners[("Random", "gravcomp")]
            run["cmaes_same"] = winners[("CMA-ES", "plain")] == winners[("CMA-ES", "gravcomp")]
            runs.append(run)
            print(f"seed {seed} {motion.name}: {time.perf_counter() - start:.0f} s", flush=True)

    saved = {
        "minutes": (time.perf_counter() - start) / 60,
        "load_start": load_start,
        "load_end": load_line(),
        "header": machine_header("cpu").rstrip(),
        "command": "python " + " ".join(shlex.quote(a) for a in sys.argv),
    }
    out = write_report(args.out, report(args, motions, uniform, nominal, runs, saved))
    print(f"wrote {out}")


def _ci(values) -> str:
    from tt.report import mean_ci

    mean, half = mean_ci(list(values))
    return f"{mean:+.1f} ± {half:.1f}"


def _mean_ci(values) -> str:
    from tt.report import mean_ci

    mean, half = mean_ci(list(values))
    return f"{mean:.1f} ± {half:.1f}"


def report(args, motions, uniform, nominal, runs, saved) -> list[str]:
    from scipy import stats

    lines = [
        "# Gravity compensation: does it change which ViperX designs win and how the methods rank?",
        "",
        saved["header"],
        f"- load average (1, 5, 15 min) at start {saved['load_start']}, at end {saved['load_end']}",
        f"- command: `{saved['command']}`",
        f"- run time {saved['minutes']:.1f} min wall (one thread for the searches' rollouts, the oracle one world "
        "at a time)",
        f"- {len(motions)} validation motions ({', '.join(m.name for m in motions)}), reward {args.reward}; "
        "'gravcomp' is the paper's evaluation (`viperx-gravcomp`: gravcomp=1 on every body, "
        "actuatorgravcomp on every joint), 'plain' tt's default (`viperx`); every reward is the oracle's "
        "(MuJoCo C + mink) under the setting named",
        "",
        f"## {args.designs} uniform designs on every motion",
        "",
        "| motion | Spearman rho | median reward plain | median reward gravcomp | tracks the whole motion plain "
        "| gravcomp | plain's best: rank under gravcomp | gravcomp's best: rank under plain |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def rank_of(scores, i) -> int:
        return int((np.asarray(scores) > scores[i]).sum()) + 1

    rhos = []
    for row in uniform:
        rho = float(stats.spearmanr(row["plain"], row["gravcomp"])[0])
        rhos.append(rho)
        bp, bg = int(np.argmax(row["plain"])), int(np.argmax(row["gravcomp"]))
        lines.append(
            f"| {row['motion']} | {rho:.3f} | {np.median(row['plain']):.1f} | {np.median(row['gravcomp']):.1f} | "
            f"{100 * np.mean(row['plain_survival'] == 1):.0f} % | {100 * np.mean(row['gravcomp_survival'] == 1):.0f} % "
            f"| {rank_of(row['gravcomp'], bp)} of {args.designs} | {rank_of(row['plain'], bg)} of {args.designs} |"
        )
    pooled = float(
        stats.spearmanr(
            np.concatenate([r["plain"] for r in uniform]), np.concatenate([r["gravcomp"] for r in uniform])
        )[0]
    )
    lines += [
        "",
        f"- Spearman rho per motion: mean {np.mean(rhos):.3f} (min {np.min(rhos):.3f}, max {np.max(rhos):.3f}); "
        f"pooled over every (design, motion): {pooled:.3f}",
        f"- mean over motions of the median reward: plain {np.mean([np.median(r['plain']) for r in uniform]):.1f}, "
        f"gravcomp {np.mean([np.median(r['gravcomp']) for r in uniform]):.1f}; tracking the whole motion: plain "
        f"{100 * np.mean([np.mean(r['plain_survival'] == 1) for r in uniform]):.1f} %, gravcomp "
        f"{100 * np.mean([np.mean(r['gravcomp_survival'] == 1) for r in uniform]):.1f} %",
        "",
        f"## Searches: Random({args.budget}) and CMA-ES({args.budget}), {args.seeds} seeds x {len(motions)} motions",
        "",
        "Mean ± 95 % CI over the runs of each winner's validated reward (rows: where the search ran; columns: "
        "where its winner is validated).",
        "",
        "| search | validated plain | validated gravcomp |",
        "|---|---:|---:|",
    ]
    for method in ("Random", "CMA-ES"):
        for s in SETTINGS:
            cells = [_mean_ci(r[f"{method} {s} winner, validated {v}"] for r in runs) for v in SETTINGS]
            lines.append(f"| {method}, run {s} | {cells[0]} | {cells[1]} |")
    lines += [
        f"| nominal ViperX (no search) | {_mean_ci(nominal['plain'])} | {_mean_ci(nominal['gravcomp'])} |",
        "",
        "### Does the winner under one setting win under the other?",
        "",
        f"- Random: the two settings screen the same {args.budget} draws; they pick the same design in "
        f"{sum(r['random_same'] for r in runs)} of {len(runs)} runs. CMA-ES: the same winner in "
        f"{sum(r['cmaes_same'] for r in runs)} of {len(runs)} runs.",
        "",
        "Cost of taking the other setting's winner: its validated reward minus this setting's own winner's, "
        "under this setting (paired, mean ± 95 % CI over the runs; share of runs where it is at least as good):",
        "",
        "| search | under plain: gravcomp's winner - plain's | at least as good | under gravcomp: plain's winner "
        "- gravcomp's | at least as good |",
        "|---|---:|---:|---:|---:|",
    ]
    for method in ("Random", "CMA-ES"):
        cells = []
        for own, other in (("plain", "gravcomp"), ("gravcomp", "plain")):
            diff = [
                r[f"{method} {other} winner, validated {own}"] - r[f"{method} {own} winner, validated {own}"]
                for r in runs
            ]
            cells += [_ci(diff), f"{sum(d >= 0 for d in diff)} of {len(diff)}"]
        lines.append(f"| {method} | {' | '.join(cells)} |")
    lines += [
        "",
        "### The methods' ranking under each setting",
        "",
        "Each search run and validated under the same setting; CMA-ES - Random paired over the runs.",
        "",
        "| setting | nominal | Random | CMA-ES | CMA-ES - Random | ranking |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for s in SETTINGS:
        rand = [r[f"Random {s} winner, validated {s}"] for r in runs]
        cma = [r[f"CMA-ES {s} winner, validated {s}"] for r in runs]
        means = {"nominal": np.mean(nominal[s]), "Random": np.mean(rand), "CMA-ES": np.mean(cma)}
        order = " > ".join(sorted(means, key=lambda k: -means[k]))
        lines.append(
            f"| {s} | {_mean_ci(nominal[s])} | {_mean_ci(rand)} | {_mean_ci(cma)} | "
            f"{_ci(np.subtract(cma, rand))} | {order} |"
        )
    seconds = {k: np.mean([r["seconds"][k] for r in runs]) for k in runs[0]["seconds"]}
    lines += [
        "",
        "- mean search time per run (s, batched warp rollouts on one thread): "
        + ", ".join(f"{k} {v:.2f}" for k, v in seconds.items()),
    ]
    return lines


if __name__ == "__main__":
    main()
