"""Does Zeroth-Order's ranking add value? Its pick against the median of its own samples.

Zeroth-Order draws n candidates and returns the one its critic ranks first. If the critic
knows nothing, that pick is a random one of the n, and beats their median half the time.
For each seed this runs Zeroth-Order (n candidates, every one decoded) on one validation
motion (the same motion per seed as `codesign.py`'s single-trajectory table), validates
every decoded candidate on the oracle (MuJoCo C + mink) and reports:

* whether the pick's validated reward beats the median of all its candidates' (the issue's
  check: at least 8 of 9 seeds);
* the Spearman correlation between the critic's predicted and the validated reward over the
  candidates (its ranking skill on its own samples);
* the pick's validated position error beside Random's and CMA-ES's (budget n, the same
  problem; their winners validated on the oracle too).

With ``--critic joint dynamics`` both critics rank the same samples (the robot task's draws do
not depend on the critic): "joint" is the paper's (the candidate's co-sampled dynamics),
"dynamics" re-predicts them with the dynamics task (`tt.guidance.zeroth`).

``--critic-checkpoint C`` adds a critic that is another checkpoint's dynamics task, the way
``tt optimize --critic-checkpoint`` uses it (`tt.guidance.zeroth.CandidateSampler`'s critic
model): it scores the sampled candidates before decoding. The robot draws do not depend on
the critic, so every critic of a seed ranks the same candidates: each is decoded and
validated once per seed (cached by its tokens and by its design).

``--rescore C [C ...]`` adds critics that are other checkpoints (e.g. a model trained on the
dynamics task alone): each scores the first critic's decoded candidates, the designs that
were validated, with `tt.guidance.predicted.predict_designs` (``--rescore-samples`` K
predictions averaged), so its rows rank exactly the same validated designs at no extra
simulation.

Usage: ``python benchmarks/zeroth_ranking.py CHECKPOINT [--seeds 9] [--n 128] [--steps 20]
[--critic joint dynamics] [--critic-samples 1 4] [--critic-checkpoint C] [--rescore C ...]
[--rescore-samples 1 4] [--baselines]``. Writes ``benchmarks/results/zeroth_ranking.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from machine import load_line, machine_header  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def seed_motions(space: str, seeds: int) -> list:
    """One validation motion per seed, cycling over skills and their variants (as `codesign.py`)."""
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, motion_set

    val = for_space(motion_set("val", arms=get_space(space).ee_count), space)
    skills = len(val) // 3
    return [val[3 * (i % skills) + i % 3] for i in range(seeds)]


class CachedDecoder:
    """A decoder that decodes each distinct candidate (by its embodiment tokens) once: the
    critics of a seed rank the same robot draws."""

    def __init__(self, decoder):
        self.decoder = decoder
        self.cache: dict[bytes, object] = {}

    def __call__(self, tokens, index: int):
        key = b"".join(
            np.ascontiguousarray(v[index]).tobytes() + np.ascontiguousarray(tokens.mask[n][index]).tobytes()
            for n, v in sorted(tokens.values.items())
        )
        if key not in self.cache:
            self.cache[key] = self.decoder(tokens, index)
        return self.cache[key]


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    from scipy import stats

    ok = np.isfinite(x) & np.isfinite(y)
    return float(stats.spearmanr(x[ok], y[ok]).statistic) if ok.sum() >= 3 else float("nan")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("--seeds", type=int, default=9)
    p.add_argument("--n", type=int, default=128, help="Zeroth-Order samples (and the baselines' budget)")
    p.add_argument("--steps", type=int, default=20, help="DDIM steps")
    p.add_argument(
        "--critic",
        nargs="+",
        default=None,
        choices=["joint", "dynamics"],
        help="critics to compare (default: the model's default critic)",
    )
    p.add_argument(
        "--critic-samples",
        type=int,
        nargs="+",
        default=[1],
        help="dynamics predictions averaged per candidate by the 'dynamics' critic (one row per value)",
    )
    p.add_argument(
        "--critic-checkpoint",
        default=None,
        help="another checkpoint whose dynamics task scores the samples (one more critic row per --critic-samples)",
    )
    p.add_argument(
        "--own-critic",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also rank with the sampling model's own critic (--no-own-critic: only --critic-checkpoint's)",
    )
    p.add_argument(
        "--rescore",
        nargs="+",
        default=[],
        metavar="CHECKPOINT",
        help="other checkpoints that score the validated designs as critics (trained on the same space)",
    )
    p.add_argument(
        "--rescore-samples",
        type=int,
        nargs="+",
        default=[1],
        help="predictions averaged per design by each --rescore critic (one row per value)",
    )
    p.add_argument("--baselines", action="store_true", help="also run Random and CMA-ES at budget n")
    p.add_argument("--space", default=None, help="design space (default: the one the checkpoint records)")
    p.add_argument("--reward", default="tracking")
    p.add_argument("--out", default=str(RESULTS / "zeroth_ranking.md"))
    args = p.parse_args()
    if args.seeds < 1 or args.n < 2 or min(args.critic_samples) < 1 or min(args.rescore_samples) < 1:
        p.error("--seeds >= 1, --n >= 2, --critic-samples >= 1 and --rescore-samples >= 1 are needed")

    from tt.baselines import CMAES, CMAESConfig, Problem, RandomSearch, evaluate_designs
    from tt.dit.checkpoint import load_model
    from tt.guidance.zeroth import DesignDecoder, SamplerConfig, ZerothOrder
    from tt.report import mean_ci
    from tt.sim.designs import get_space

    trained = load_model(args.checkpoint, device="cpu")
    space = trained.space or args.space
    if space is None:
        p.error("the checkpoint records no design space (made before checkpoints did); give --space")
    if args.space is not None and args.space != space:
        p.error(f"--space {args.space} but the checkpoint was trained on {space}")
    from tt.guidance.predicted import check_space, predict_designs
    from tt.sim.rewards import get_reward

    rescorers = []
    for path in args.rescore:
        other = load_model(path, device="cpu")
        check_space(other, space)
        rescorers.append((path, other))
    judge = None
    if args.critic_checkpoint is not None:
        judge = load_model(args.critic_checkpoint, device="cpu")
        check_space(judge, space)
    sp = get_space(space)
    decoder = CachedDecoder(DesignDecoder(sp))
    critics = [(c, k, None) for c in (args.critic or [None]) for k in (args.critic_samples if c == "dynamics" else [1])]
    if not args.own_critic:
        critics = []
    if judge is not None:
        critics += [("dynamics", k, judge) for k in args.critic_samples]
    if not critics:
        p.error("--no-own-critic needs --critic-checkpoint")
    load_start = load_line()
    start = time.perf_counter()
    rows = []
    for seed, motion in enumerate(seed_motions(space, args.seeds)):
        problem = Problem(space, (motion,), args.reward, args.n, seed=seed, backend="warp", device="cpu")
        checked: dict[str, tuple[float, float]] = {}  # design -> validated (reward, position error)
        for critic, k, model in critics:
            zo = ZerothOrder(
                SamplerConfig(num_steps=args.steps, decode="all", critic=critic, critic_samples=k),
                model=trained,
                decoder=decoder,
                critic_model=model,
            )
            res = zo.optimize(problem)
            keys = [json.dumps(sp.to_dict(d), sort_keys=True) for d in res.designs]
            todo = [key for key in dict.fromkeys(keys) if key not in checked]
            if todo:
                ev = evaluate_designs(
                    [res.designs[keys.index(key)] for key in todo], (motion,), args.reward, backend="mujoco"
                )
                for j, key in enumerate(todo):
                    checked[key] = (float(ev.reward[j, 0]), float(np.asarray(ev.metrics["pos_err"])[j, 0]))
            validated = np.array([checked[key][0] for key in keys])
            pos_err = np.array([checked[key][1] for key in keys])
            label = (
                res.info["critic"]
                + (f" of `{args.critic_checkpoint}`" if model is not None else "")
                + (" on the decoded designs" if res.info.get("critic_on") == "designs" else "")
                + (f" (mean of {k} predictions)" if k > 1 else "")
            )
            row = {
                "bench": "zeroth_ranking",
                "seed": seed,
                "motion": motion.name,
                "critic": label,
                "decoded": len(res.designs),
                "pick_reward": float(validated[0]),
                "median_reward": float(np.median(validated)),
                "best_reward": float(validated.max()),
                "pick_beats_median": bool(validated[0] > np.median(validated)),
                "spearman": spearman(np.asarray(res.rewards), validated),
                "pick_pos_err": float(pos_err[0]),
                "seconds": res.seconds,
            }
            print(json.dumps(row), flush=True)
            rows.append(row)
            if rescorers and (critic, k, model) == critics[0]:
                for path, other in rescorers:
                    for ks in args.rescore_samples:
                        pred = predict_designs(
                            other,
                            res.designs,
                            (motion,),
                            get_reward(args.reward, space),
                            samples=ks,
                            num_steps=args.steps,
                            seed=seed,
                        )
                        score = pred.reward[:, 0]
                        pick = int(np.nanargmax(np.where(np.isfinite(score), score, -np.inf)))
                        label = f"`{path}` rescoring" + (f" (mean of {ks} predictions)" if ks > 1 else "")
                        extra = {
                            **row,
                            "critic": label,
                            "pick_reward": float(validated[pick]),
                            "pick_beats_median": bool(validated[pick] > np.median(validated)),
                            "spearman": spearman(score, validated),
                            "pick_pos_err": float(pos_err[pick]),
                            "seconds": pred.seconds,
                        }
                        print(json.dumps(extra), flush=True)
                        rows.append(extra)
        if args.baselines:
            for name, opt in (("Random", RandomSearch()), ("CMA-ES", CMAES(CMAESConfig()))):
                res = opt.optimize(problem)
                ev = evaluate_designs([res.best], (motion,), args.reward, backend="mujoco")
                row = {
                    "bench": "zeroth_ranking",
                    "seed": seed,
                    "motion": motion.name,
                    "critic": name,
                    "pick_reward": float(ev.reward[0, 0]),
                    "pick_pos_err": float(np.asarray(ev.metrics["pos_err"])[0, 0]),
                    "seconds": res.seconds,
                }
                print(json.dumps(row), flush=True)
                rows.append(row)
    minutes = (time.perf_counter() - start) / 60

    lines = [
        "# Zeroth-Order's ranking against the median of its own samples",
        "",
        machine_header("cpu"),
        f"- command: `python benchmarks/zeroth_ranking.py {' '.join(sys.argv[1:])}`",
        f"- checkpoint: `{args.checkpoint}` (space {space}, tasks {list(trained.tasks)}, step {trained.step})",
        *(
            [f"- critic checkpoint: `{args.critic_checkpoint}` (tasks {list(judge.tasks)}, step {judge.step})"]
            if judge is not None
            else []
        ),
        *[f"- rescoring critic: `{path}` (tasks {list(other.tasks)}, step {other.step})" for path, other in rescorers],
        f"- load: {load_start} at the start, {load_line()} at the end; {minutes:.1f} min wall",
        "",
        f"{args.seeds} seeds, each one validation motion, Zeroth-Order with n = {args.n} ({args.steps} DDIM steps), "
        "every decoded candidate validated on the oracle. Target (issue 17): the pick beats the median of its "
        "own samples in at least 8 of 9 seeds.",
        "",
        "| critic | pick beats median (seeds) | pick / median / best validated reward (mean ± 95% CI) | "
        "Spearman predicted vs validated | pick's position error (cm) |",
        "|---|---:|---|---|---|",
    ]

    def fmt(values, scale: float = 1.0) -> str:
        m, h = mean_ci([v * scale for v in values])
        return f"{m:.1f} ± {h:.1f}" if np.isfinite(h) else f"{m:.1f}"

    for critic in dict.fromkeys(r["critic"] for r in rows):
        sel = [r for r in rows if r["critic"] == critic]
        err = fmt([r["pick_pos_err"] for r in sel])  # the metric is in cm
        if "median_reward" in sel[0]:
            wins = sum(r["pick_beats_median"] for r in sel)
            lines.append(
                f"| Zeroth-Order, {critic} critic | {wins} of {len(sel)} | {fmt([r['pick_reward'] for r in sel])} / "
                f"{fmt([r['median_reward'] for r in sel])} / {fmt([r['best_reward'] for r in sel])} | "
                f"{fmt([r['spearman'] for r in sel])} | {err} |"
            )
        else:
            lines.append(f"| {critic} (budget {args.n}) | | {fmt([r['pick_reward'] for r in sel])} | | {err} |")
    lines += [
        "",
        "Per seed:",
        "",
        "| seed | motion | critic | pick | median | best | Spearman |",
        "|---:|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "median_reward" in r:
            lines.append(
                f"| {r['seed']} | {r['motion']} | {r['critic']} | {r['pick_reward']:.1f} | {r['median_reward']:.1f} | "
                f"{r['best_reward']:.1f} | {r['spearman']:.2f} |"
            )
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
