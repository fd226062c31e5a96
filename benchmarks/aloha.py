"""The paper's ALOHA experiment: the original ALOHA against Random, CMA-ES and the learned
methods on the bimanual validation flings, reward "Tracking Velocity", winners on the oracle.

The paper fabricated an ALOHA optimized by its model for the "Tracking Velocity" reward on a
bimanual cloth fling and reports, against the original design, tracking error 13.0 -> 3.5 cm
(-73 %) and max joint speed 2.57 -> 1.82 rad/s (-30 %), measured on the real robots. This
runs the same comparison in simulation:

* Problems: run i (seed i, i = 0 .. --seeds - 1) optimizes one design for the i-th fling of
  the bimanual validation set (``motion_set("val", arms=2)``, the ``bi_fling`` ones, i mod
  their count), placed for the ALOHA (`tt.sim.motions.for_space`), reward
  ``tracking_velocity`` (`--reward`), budget `--budget` candidates, on the space's default
  backend (tt's batched Warp kernels).
* Methods: Random (the best of `--budget` random designs, one batched rollout) and batched
  CMA-ES (tt optimize's default configuration, `--budget` rollouts), and Random again at
  CMA-ES's wall time on the same run ("Random (= time)": its budget scaled by the ratio of
  the two methods' times at `--budget`), for the comparison at equal wall time. Where the
  space ships a generator (`checkpoints/aloha_mini_robot.pt`, or `--checkpoint`), also the
  paper's Zeroth-Order (`--budget` samples ranked by the shipped critic, the best one
  returned) and tt's best hybrid, CMA-ES started from the model's samples (`--budget`
  rollouts), with Random at the hybrid's wall time ("Random (= model time)").
* Validation: the original design (the space's nominal one, `tt designs --space aloha
  --nominal`) and every winner re-run on the MuJoCo + mink oracle on the run's fling, in
  one call per run.
* Report: validated position error and max joint speed (`tt.sim.rewards.metrics`:
  ``max_joint_speed``, the largest |qdot| of any actuator at any counted step), each as the
  relative change from the original on the same fling, mean over the runs with the 95 %
  Student-t interval of the paired per-run changes; wall time per method (optimize only:
  the kernel compile or cache load and first calls happen in the optimizers' warm-up,
  excluded and reported on its own line); which of Random and CMA-ES wins at equal time
  (paired difference of the validated reward).

Writes benchmarks/results/aloha.md (or ``--out``) and the runs as JSON lines to ``--log``
(default runs/benchmarks/aloha.jsonl, outside the results folder); prints one JSON line per
run. ``--from-log FILE.jsonl`` rewrites the report from such lines. Run from the repository
root: ``python benchmarks/aloha.py`` (9 runs of 128 candidates: a few minutes on a 2-core CPU).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from tt.baselines import CMAES, CMAESConfig, Problem, RandomSearch, evaluate_designs
from tt.report import mean_ci, summary_row
from tt.sim.designs import get_space
from tt.sim.motions import for_space, motion_set
from tt.sim.rewards import reward_name

try:
    from codesign import CMAES_INIT as CODESIGN_INIT
    from codesign import ZEROTH as CODESIGN_ZEROTH
    from codesign import load_learned, optimizer
    from machine import load_line, machine_header, write_report
except ImportError:  # run as a module from the repository root
    from benchmarks.codesign import CMAES_INIT as CODESIGN_INIT
    from benchmarks.codesign import ZEROTH as CODESIGN_ZEROTH
    from benchmarks.codesign import load_learned, optimizer
    from benchmarks.machine import load_line, machine_header, write_report

RESULTS = Path(__file__).parent / "results"
#: Logs of runs: outside the repository's tree of results (runs/ is not tracked).
RUNS = Path(__file__).resolve().parents[1] / "runs" / "benchmarks"
SPACE = "aloha"
ORIGINAL, RANDOM, CMAES_B, RANDOM_T = "Original ALOHA", "Random", "CMA-ES batched", "Random (= time)"
#: The learned methods (with a generator for the space): the paper's Zeroth-Order (the critic
#: ranks the model's samples, one rollout) and tt's best hybrid (CMA-ES started from the model's
#: samples, benchmarks/results/codesign_hybrid9.md), and Random at the hybrid's wall time.
ZEROTH, CMAES_INIT, RANDOM_TM = "Zeroth-Order", "CMA-ES from the model", "Random (= model time)"
BASELINES = (RANDOM, CMAES_B, RANDOM_T)
LEARNED = (ZEROTH, CMAES_INIT, RANDOM_TM)
METHODS = BASELINES + LEARNED
#: The paper's ALOHA result (real robots, the original design against the model's optimized
#: one): (original, optimized, the paper's relative change in %).
PAPER = {"pos_err": (13.0, 3.5, -73), "max_joint_speed": (2.57, 1.82, -30)}
#: The issue's targets: the optimized design at least this much below the original (relative).
TARGETS = {"pos_err": -0.70, "max_joint_speed": -0.30}
METRICS = (("pos_err", "position error", "cm"), ("max_joint_speed", "max joint speed", "rad/s"))


def fling_motions() -> list:
    """The bimanual validation flings, placed for the ALOHA."""
    flings = [m for m in motion_set("val", arms=2) if m.name.startswith("bi_fling")]
    return for_space(flings, SPACE)


def run_one(seed: int, motion, args, learned=None, quiet: bool = False) -> list[dict]:
    """Random, CMA-ES and Random at CMA-ES's time on one fling, and with `learned` (a loaded
    generator and critic, `benchmarks/codesign.py`'s `load_learned`) Zeroth-Order, CMA-ES from
    the model's samples and Random at the latter's time; the original and the winners
    validated on the oracle in one call. One record per design."""
    space = get_space(SPACE)

    def problem(budget: int) -> Problem:
        return Problem(SPACE, (motion,), args.reward, budget, seed=seed, device="cpu", threads=args.threads)

    cmaes = CMAES(CMAESConfig(popsize=args.popsize, generations=args.generations))
    results = {RANDOM: RandomSearch().optimize(problem(args.budget)), CMAES_B: cmaes.optimize(problem(args.budget))}
    t_random = results[RANDOM].seconds

    def at_time(seconds: float):  # Random given `seconds`: its budget scaled by the time ratio
        return RandomSearch().optimize(problem(max(1, int(round(args.budget * seconds / max(t_random, 1e-9))))))

    results[RANDOM_T] = at_time(results[CMAES_B].seconds)
    if learned is not None:  # built as benchmarks/codesign.py builds them
        cfg = argparse.Namespace(
            steps=args.ddim_steps, critic_samples=1, popsize=args.popsize, generations=args.generations
        )
        results[ZEROTH] = optimizer(CODESIGN_ZEROTH, cfg, learned).optimize(problem(args.budget))
        results[CMAES_INIT] = optimizer(CODESIGN_INIT, cfg, learned).optimize(problem(args.budget))
        results[RANDOM_TM] = at_time(results[CMAES_INIT].seconds)
    labels = [m for m in METHODS if m in results]
    designs = [space.nominal()] + [results[m].best for m in labels]
    ev = evaluate_designs(designs, [motion], args.reward, backend="mujoco")
    records = []
    for k, (label, design) in enumerate(zip([ORIGINAL] + labels, designs)):
        rec = {"bench": "aloha", "seed": seed, "motion": motion.name, "reward_name": args.reward, "method": label}
        if label != ORIGINAL:
            res = results[label]
            rec.update(
                budget=args.budget if label == ZEROTH else len(res.designs),  # Zeroth-Order returns its best sample
                rollouts=res.rollouts,
                seconds=res.seconds,
                warmup_seconds=res.info.get("warmup_seconds", 0.0),
                objective=res.best_reward,
            )
        rec.update(summary_row(ev.metrics, k), design=space.to_dict(design))
        records.append(rec)
        if not quiet:
            print(json.dumps(rec), flush=True)
    return records


# ------------------------------------------------------------------------------ statistics
def _by(records: list[dict], method: str) -> dict[int, dict]:
    return {r["seed"]: r for r in records if r["method"] == method}


def relative_changes(records: list[dict], method: str, key: str) -> list[float]:
    """Per run: (method - original) / original of `key` on the run's fling (finite pairs only)."""
    orig, mine = _by(records, ORIGINAL), _by(records, method)
    out = []
    for seed in sorted(set(orig) & set(mine)):
        a, b = mine[seed].get(key), orig[seed].get(key)
        if a is not None and b is not None and math.isfinite(a) and math.isfinite(b) and b != 0:
            out.append((a - b) / b)
    return out


def paired(records: list[dict], a: str, b: str, key: str) -> list[float]:
    """Per run: a's `key` minus b's (finite pairs only)."""
    ra, rb = _by(records, a), _by(records, b)
    out = []
    for seed in sorted(set(ra) & set(rb)):
        x, y = ra[seed].get(key), rb[seed].get(key)
        if x is not None and y is not None and math.isfinite(x) and math.isfinite(y):
            out.append(x - y)
    return out


def _ci(values, digits: int = 3) -> str:
    m, h = mean_ci(values)
    if not math.isfinite(m):
        return "-"
    return f"{m:.{digits}g}" + (f" ± {h:.2g}" if math.isfinite(h) else "")


def _pct(values) -> str:
    m, h = mean_ci(values)
    if not math.isfinite(m):
        return "-"
    return f"{100 * m:+.0f} %" + (f" ± {100 * h:.0f}" if math.isfinite(h) else "")


def _holds0(values) -> str:
    """ " (the interval holds 0)" where the 95 % interval of `values`' mean holds 0, else ""."""
    m, h = mean_ci(values)
    return " (the interval holds 0)" if math.isfinite(h) and m - h <= 0 <= m + h else ""


def _span(values) -> str:
    """Mean relative change and its 95 % interval in percent: "-56 % (-60 to -52 %)"."""
    c, lo, hi = _pct_ci(values)
    if not math.isfinite(c):
        return "-"
    return f"{c:+.0f} %" + (f" ({lo:+.0f} to {hi:+.0f} %)" if len(values) > 1 else " (one run)")


def _pct_ci(values) -> tuple[float, float, float]:
    """Mean relative change and its 95 % interval (low, high), in percent."""
    m, h = mean_ci(values)
    h = h if math.isfinite(h) else 0.0
    return 100 * m, 100 * (m - h), 100 * (m + h)


def equal_time(records: list[dict], a: str, b: str, budget) -> list[str]:
    """Method `a` against Random given `a`'s wall time (`b`), paired per run: which wins."""
    t_a = [r["seconds"] for r in records if r["method"] == a]
    t_b = [r["seconds"] for r in records if r["method"] == b]
    d_rew = paired(records, a, b, "reward")
    if not d_rew:
        return [f"- {a}: no paired runs"]
    m, h = mean_ci(d_rew)
    wins = sum(d > 0 for d in d_rew)
    if math.isfinite(h) and m - h > 0:
        verdict = f"{a} wins"
    elif math.isfinite(h) and m + h < 0:
        verdict = "Random wins"
    elif not math.isfinite(h):
        verdict = (a if m > 0 else "Random") + " ahead (one run: no interval)"
    else:
        verdict = "neither wins clearly (the interval holds 0); " + (a if m > 0 else "Random") + " ahead"
    d_err, d_spd = paired(records, a, b, "pos_err"), paired(records, a, b, "max_joint_speed")
    out = [
        f"{a} against Random given its wall time (Random's budget scaled by the ratio of their times at {budget} "
        f"candidates: {_ci([r['budget'] for r in records if r['method'] == b], 4)} candidates in {_ci(t_b)} s, "
        f"{a} {_ci(t_a)} s), paired per run, {a} minus Random:",
        "",
        f"- validated reward: {_ci(d_rew)} ({a} higher in {wins} of {len(d_rew)} run(s)): **{verdict}**",
        f"- position error: {_ci(d_err)} cm{_holds0(d_err)}; max joint speed: {_ci(d_spd)} rad/s{_holds0(d_spd)}",
    ]
    d_eq = paired(records, a, RANDOM, "reward")
    if d_eq:
        out.append(
            f"- at equal candidates ({budget} each), {a} minus Random: validated reward {_ci(d_eq)}{_holds0(d_eq)}"
        )
    return out + [""]


# ------------------------------------------------------------------------------ report
def report(records: list[dict], info: dict, out: Path) -> str:
    runs = sorted({r["seed"] for r in records})
    methods = [m for m in (ORIGINAL,) + METHODS if any(r["method"] == m for r in records)]
    lines = [
        "# ALOHA: the original design against Random, CMA-ES and the learned methods on the bimanual flings",
        "",
        'The paper\'s ALOHA result (optimized for the "Tracking Velocity" reward on a bimanual cloth fling) '
        "with tt's baselines and, where a generator was given, its learned methods; `python benchmarks/aloha.py` "
        "(the module docstring says what it runs).",
        "",
        machine_header("cpu").rstrip("\n"),
        f"- runs measured {info.get('date', '?')}",
        f"- load (1, 5, 15 min) at start: {info.get('load_start', '?')}; at end: {info.get('load_end', '?')}",
        f"- command: `{info.get('command', 'python benchmarks/aloha.py')}`",
        f"- {len(runs)} run(s) (run i: seed i on fling i mod {len(info.get('motions', [])) or '?'}: "
        f"{', '.join(info.get('motions', []))}), reward `{info.get('reward', 'tracking_velocity')}`, budget "
        f"{info.get('budget', '?')} candidates; CMA-ES batched: population {info.get('popsize', '?')}, "
        f"{info.get('generations', '?')} generations per restart (tt optimize's default); winners and the original "
        "validated on the MuJoCo + mink oracle",
        f"- run time {info.get('wall_seconds', float('nan')):.0f} s wall; the optimizers' warm-up (kernel compile "
        f"or cache load, first calls; not in the optimize times) {info.get('warmup_seconds', float('nan')):.1f} s "
        "in all",
        "",
        "## Validated on the oracle",
        "",
        "Mean over the runs ± the 95 % Student-t half-width. Changes: each run's relative change from the "
        "original design on the same fling (paired), then their mean ± half-width. Max joint speed: the largest "
        "|qdot| of any actuator at any counted step of the episode; velocity: the mean over the counted steps of "
        "|qdot|_2 over the actuators (what the reward penalises, squared).",
        "",
        "| design | pos err (cm) | change | max joint speed (rad/s) | change | velocity (rad/s) | change "
        "| survival (%) | reward | optimize (s) | candidates |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in methods:
        rs = [r for r in records if r["method"] == m]
        cells = [
            m,
            _ci([r.get("pos_err") for r in rs]),
            "-" if m == ORIGINAL else _pct(relative_changes(records, m, "pos_err")),
            _ci([r.get("max_joint_speed") for r in rs]),
            "-" if m == ORIGINAL else _pct(relative_changes(records, m, "max_joint_speed")),
            _ci([r.get("velocity") for r in rs]),
            "-" if m == ORIGINAL else _pct(relative_changes(records, m, "velocity")),
            _ci([r.get("survival_pct") for r in rs]),
            _ci([r.get("reward") for r in rs]),
            "-" if m == ORIGINAL else _ci([r["seconds"] for r in rs]),
            "-" if m == ORIGINAL else _ci([r["budget"] for r in rs], 4),
        ]
        lines.append("| " + " | ".join(cells) + " |")

    beside = [m for m in (CMAES_B, RANDOM, ZEROTH, CMAES_INIT) if m in methods]
    lines += ["", "## Beside the paper", ""]
    lines += [
        "The paper's numbers are the fabricated robots' (its model's optimized design, measured in the real "
        "world); tt's are simulated (the baselines' winners on the oracle). Original → optimized, the means over "
        "the runs, and the mean paired relative change with its 95 % interval.",
        "",
        "| metric | paper (real robots) | " + " | ".join(f"tt, {m}" for m in beside) + " |",
        "|---|---|" + "---|" * len(beside),
    ]
    orig = [r for r in records if r["method"] == ORIGINAL]
    for key, name, unit in METRICS:
        p0, p1, pct = PAPER[key]
        row = [f"{name} ({unit})", f"{p0:.2f} → {p1:.2f} ({pct:+d} %)"]
        for m in beside:
            rs = [r for r in records if r["method"] == m]
            o, w = mean_ci([r.get(key) for r in orig])[0], mean_ci([r.get(key) for r in rs])[0]
            row.append(f"{o:.2f} → {w:.2f}: {_span(relative_changes(records, m, key))}" if rs else "-")
        lines.append("| " + " | ".join(row) + " |")

    lines += ["", "## Targets", ""]
    for m in methods[1:]:
        parts = []
        for key, name, _ in METRICS:
            ch = relative_changes(records, m, key)
            if not ch:
                parts.append(f"{name}: no run")
                continue
            c, _, hi = _pct_ci(ch)
            goal = 100 * TARGETS[key]
            if len(ch) < 2:
                verdict = ("met" if c <= goal else "not met") + " (one run: no interval)"
            else:
                verdict = (
                    "met" if hi <= goal else ("met on the mean, not the whole interval" if c <= goal else "not met")
                )
            parts.append(f"{name} {_span(ch)} (target ≤ {goal:+.0f} %): {verdict}")
        lines.append(f"- {m}: " + "; ".join(parts))

    lines += ["", "## At equal wall time", ""]
    for a, b in ((CMAES_B, RANDOM_T), (CMAES_INIT, RANDOM_TM)):
        if a in methods and b in methods:
            lines += equal_time(records, a, b, info.get("budget"))
    lines += ["", "## Reading", ""]
    for m in beside:
        v, j = relative_changes(records, m, "velocity"), relative_changes(records, m, "max_joint_speed")
        if v and j:
            lines.append(
                f"- {m}: the winners of the velocity reward change the mean joint-velocity norm by {_span(v)} from "
                f"the original, the max joint speed by {_span(j)}"
                + (
                    ": the fling's peak still asks some joint for nearly the original's speed."
                    if abs(mean_ci(j)[0]) < abs(mean_ci(v)[0]) / 2
                    else "."
                )
            )
    same = [
        seed
        for seed, r in _by(records, CMAES_B).items()
        if seed in _by(records, RANDOM) and _by(records, RANDOM)[seed]["design"] == r["design"]
    ]
    if same:
        lines.append(
            f"- CMA-ES returned Random's winner in {len(same)} of {len(runs)} runs (runs {', '.join(map(str, same))}): "
            "its screen (half the budget) is the first half of the same seed's random draws, and no restart beat "
            "that screen's best."
        )

    lines += ["", "## Per run", ""]
    head = ["run", "fling"] + [f"{m}: pos err (cm) / max joint speed (rad/s)" for m in methods]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for seed in runs:
        rs = {r["method"]: r for r in records if r["seed"] == seed}
        cells = [str(seed), next(iter(rs.values()))["motion"]]
        for m in methods:
            r = rs.get(m, {})
            cells.append(f"{r.get('pos_err', float('nan')):.2f} / {r.get('max_joint_speed', float('nan')):.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    path = write_report(out, lines)
    return str(path)


def load_generator(args):
    """The generator and critic of the learned methods (`--checkpoint`, default the space's
    shipped pair), loaded once; None where the space ships no generator."""
    from tt.dit.checkpoint import NoCheckpointError, default_checkpoint, shipped_critic

    if args.checkpoint is None:
        try:
            args.checkpoint = default_checkpoint(SPACE, task="robot")
        except NoCheckpointError:
            return None
    if args.critic_checkpoint is None:
        args.critic_checkpoint = shipped_critic(SPACE, args.checkpoint)
    return load_learned(SPACE, args.checkpoint, args.critic_checkpoint)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=9, help="runs: seed i on fling i mod the flings' count")
    ap.add_argument("--budget", type=int, default=128, help="candidates of Random and CMA-ES per run")
    ap.add_argument("--reward", default="tracking_velocity", help="reward (tt's name or the paper's)")
    ap.add_argument("--popsize", type=int, default=5, help="CMA-ES population")
    ap.add_argument("--generations", type=int, default=3, help="CMA-ES generations per restart")
    ap.add_argument("--steps", type=int, default=None, help="smoke test: the flings' first N steps only")
    ap.add_argument("--threads", type=int, default=None, help="CPU threads of the warp rollouts (default: all)")
    ap.add_argument("--out", type=Path, default=RESULTS / "aloha.md", help="report")
    ap.add_argument("--log", type=Path, default=RUNS / "aloha.jsonl", help="the runs as JSON lines")
    ap.add_argument("--from-log", type=Path, default=None, help="rewrite the report from a .jsonl of runs")
    ap.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="the learned methods' generator (default: the space's shipped one; none shipped: baselines only)",
    )
    ap.add_argument(
        "--critic-checkpoint", type=Path, default=None, help="Zeroth-Order's critic (default: the shipped one)"
    )
    ap.add_argument("--ddim-steps", type=int, default=20, help="DDIM steps of the learned methods (of 100)")
    ap.add_argument("--baselines-only", action="store_true", help="skip the learned methods")
    args = ap.parse_args()
    args.reward = reward_name(args.reward)
    if args.from_log is not None:
        lines = [json.loads(x) for x in args.from_log.read_text().splitlines() if x.strip()]
        info = next((x["config"] for x in lines if "config" in x), {})
        records = [x for x in lines if x.get("bench") == "aloha" and "method" in x]
        print(f"wrote {report(records, info, args.out)}")
        return

    t0 = time.perf_counter()
    motions = fling_motions()
    if args.steps is not None:
        from tt.sim.motions.base import Motion

        motions = [Motion(m.name, m.pos[: args.steps], m.quat[: args.steps], m.dt) for m in motions]
    info = {
        "command": " ".join(["python", "benchmarks/aloha.py", *sys.argv[1:]]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_start": load_line(),
        "motions": [m.name for m in motions],
        "reward": args.reward,
        "budget": args.budget,
        "popsize": args.popsize,
        "generations": args.generations,
        "seeds": args.seeds,
        "steps": args.steps,
    }
    learned = None if args.baselines_only else load_generator(args)
    if learned is not None:
        info.update(
            checkpoint=str(learned.checkpoint),
            critic=None if learned.critic is None else str(args.critic_checkpoint),
            ddim_steps=args.ddim_steps,
            learned_seconds=learned.seconds,
        )
        # First calls (model warm-up, decoder, kernels) outside the timed runs.
        run_one(
            0,
            motions[0],
            argparse.Namespace(**{**vars(args), "budget": 4 * args.popsize, "ddim_steps": 2}),
            learned,
            quiet=True,
        )
    records: list[dict] = []
    for seed in range(args.seeds):
        records += run_one(seed, motions[seed % len(motions)], args, learned)
    info["wall_seconds"] = time.perf_counter() - t0
    info["warmup_seconds"] = sum(r.get("warmup_seconds", 0.0) for r in records)
    info["load_end"] = load_line()
    log = args.log
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text("\n".join(json.dumps(x) for x in [{"bench": "aloha", "config": info}] + records) + "\n")
    print(f"wrote {report(records, info, args.out)} and {log} in {info['wall_seconds']:.0f} s")


if __name__ == "__main__":
    main()
