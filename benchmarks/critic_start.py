"""Does the critic's slope follow the simulator's once the start is held fixed? (issue 17, Self-Guidance)

Critic guidance (`tt.guidance.critic_grad`) differentiates a critic trained told each
episode's simulated start (`tt train --dynamics-start`); the start is computed for the
design x0_hat decodes to and enters the critic as a constant, so the gradient cannot see how
a change of the design moves the start. The start is what separates failing designs from
tracking ones (`critic_failures.md`). This measures, on one structure (R1,
`viperx-nominal`) where the design's continuous choices are all that change, the change of
the tracking reward along random directions of those choices, by central differences:

* simulated: the Warp rollout of each perturbed design (the truth);
* critic, start re-simulated: `tt.guidance.predicted.predict_designs` on each perturbed
  design, told its own simulated start (what `tt predict` does; not differentiable);
* critic, start fixed: the same, told the unperturbed design's start (what the guidance
  gradient sees).

Both critic columns use the same sampling noise for the + and - design of a pair (one call
per group with the same seed), so their difference is the design's and the start's effect,
not noise. Reported: Pearson and Spearman r of each critic difference with the simulated
one over all (design, direction, motion) triples, and how often the signs agree where the
simulated change is clear.

Usage: ``python benchmarks/critic_start.py [--designs 16] [--directions 4] [--step 0.05]``;
writes ``benchmarks/results/critic_start.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from dit_eval import RESULTS, validation_motions  # noqa: E402
from machine import machine_header, write_report  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SPACE = "viperx-nominal"


def emit(**fields) -> dict:
    print(json.dumps({"bench": "critic_start", **fields}), flush=True)
    return fields


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    rank = lambda x: np.argsort(np.argsort(x)).astype(float)  # noqa: E731
    return float(np.corrcoef(rank(a), rank(b))[0, 1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--critic",
        default=str(ROOT / "checkpoints" / "viperx-nominal_mini_dynamics.pt"),
        help="a dynamics critic of viperx-nominal trained told the start (--dynamics-start)",
    )
    parser.add_argument("--designs", type=int, default=16, help="unperturbed designs")
    parser.add_argument("--directions", type=int, default=4, help="random directions per design")
    parser.add_argument(
        "--step", type=float, default=0.05, help="half step of a central difference, as a share of each choice's range"
    )
    parser.add_argument("--motions", type=int, default=5, help="validation motions")
    parser.add_argument("--seed", type=int, default=20261205, help="designs, directions and the critic's noise")
    parser.add_argument(
        "--clear", type=float, default=1.0, help="a simulated change counts as clear above this (reward units)"
    )
    parser.add_argument("--out", default=str(RESULTS / "critic_start.md"))
    args = parser.parse_args()
    if not 0 < args.step <= 0.1:
        parser.error(f"--step {args.step}: must be in (0, 0.1] (designs are pulled to the middle 80 % of each range)")
    import torch
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    import tt.guidance.predicted as predicted
    from tt.baselines.evaluate import evaluate_designs
    from tt.dit.checkpoint import load_model
    from tt.sim.designs import Design, get_space
    from tt.sim.rewards import get_reward

    torch.set_num_threads(2)
    load_before = os.getloadavg()
    started = time.perf_counter()
    space = get_space(SPACE)
    critic = load_model(args.critic, device="cpu")
    if not critic.dynamics_start:
        parser.error(f"{args.critic} was not trained told the start (--dynamics-start): nothing to hold fixed")
    motions = validation_motions(args.motions)
    cfg = get_reward("tracking", SPACE)
    rng = np.random.default_rng(args.seed)
    K, J = args.designs, args.directions
    raw = space.sample(K, seed=args.seed)
    params = space.continuous_params(raw[0].discrete)
    low = np.array([p.low for p in params])
    span = np.array([p.high for p in params]) - low
    u = 0.1 + 0.8 * rng.random((K, len(params)))  # inside the bounds by more than any step
    dirs = rng.normal(size=(K, J, len(params)))
    dirs /= np.abs(dirs).max(axis=2, keepdims=True)  # each choice moves at most one step
    make = lambda x: Design(SPACE, raw[0].discrete, tuple(float(v) for v in low + x * span))  # noqa: E731
    base = [make(u[k]) for k in range(K)]
    plus = [[make(u[k] + args.step * dirs[k, j]) for k in range(K)] for j in range(J)]
    minus = [[make(u[k] - args.step * dirs[k, j]) for k in range(K)] for j in range(J)]

    t = time.perf_counter()
    every = base + [d for j in range(J) for d in plus[j] + minus[j]]
    sim = evaluate_designs(every, motions, "tracking").reward  # (K (1 + 2J), M)
    sim_s = time.perf_counter() - t
    sim_p = np.stack([sim[K + 2 * j * K : K + (2 * j + 1) * K] for j in range(J)])  # (J, K, M)
    sim_m = np.stack([sim[K + (2 * j + 1) * K : K + (2 * j + 2) * K] for j in range(J)])

    def predict(designs, first=None) -> np.ndarray:
        """(K, M) predicted rewards; first: start tokens to give instead of the designs' own."""
        if first is None:
            return predicted.predict_designs(critic, designs, motions, cfg, seed=args.seed).reward
        own = predicted.start_tokens
        predicted.start_tokens = lambda *a, **k: first  # the unperturbed designs' start, row for row
        try:
            return predicted.predict_designs(critic, designs, motions, cfg, seed=args.seed).reward
        finally:
            predicted.start_tokens = own

    t = time.perf_counter()
    base_first = predicted.start_tokens(critic.layout, critic.normalizer, base, motions, device="cpu")
    crit_base = predict(base)
    own_p = np.stack([predict(plus[j]) for j in range(J)])
    own_m = np.stack([predict(minus[j]) for j in range(J)])
    fix_p = np.stack([predict(plus[j], base_first) for j in range(J)])
    fix_m = np.stack([predict(minus[j], base_first) for j in range(J)])
    critic_s = time.perf_counter() - t

    d_sim = (sim_p - sim_m).ravel()
    d_own = (own_p - own_m).ravel()
    d_fix = (fix_p - fix_m).ravel()
    clear = np.abs(d_sim) > args.clear
    rows = []
    for label, d in (
        ("critic, start re-simulated (what `tt predict` sees)", d_own),
        ("critic, start fixed at the unperturbed design's (what the guidance gradient sees)", d_fix),
    ):
        rows.append(
            emit(
                label=label,
                pearson=float(np.corrcoef(d, d_sim)[0, 1]),
                spearman=spearman(d, d_sim),
                sign=float(np.mean(np.sign(d[clear]) == np.sign(d_sim[clear]))) if clear.any() else float("nan"),
                rms=float(np.sqrt(np.mean(d**2))),
            )
        )
    level = emit(
        base_pearson=float(np.corrcoef(crit_base.ravel(), sim[:K].ravel())[0, 1]),
        sim_rms=float(np.sqrt(np.mean(d_sim**2))),
        clear=int(clear.sum()),
        triples=int(d_sim.size),
        sim_seconds=sim_s,
        critic_seconds=critic_s,
    )
    load_after = os.getloadavg()
    lines = [
        "# The critic's slope along the design, with and without the start held fixed (R1, viperx-nominal)",
        "",
        machine_header("cpu").rstrip(),
        f"- torch threads {torch.get_num_threads()}; load average (1 min) before / after: {load_before[0]:.1f} / "
        f"{load_after[0]:.1f}; {time.perf_counter() - started:.0f} s in all (simulation {sim_s:.0f} s, critic "
        f"{critic_s:.0f} s)",
        f"- command: `python benchmarks/critic_start.py {' '.join(sys.argv[1:])}`",
        f"- critic: `{Path(args.critic).relative_to(ROOT) if Path(args.critic).is_relative_to(ROOT) else args.critic}` "
        f"(step {critic.step}), told each episode's simulated start; {predicted.CRITIC_DDIM_STEPS} DDIM "
        "steps, one sample, "
        f"the same noise for the + and - design of every pair",
        f"- {K} {SPACE} designs (seed {args.seed}, each continuous choice drawn from the middle 80 % of its range) x "
        f"{J} random directions (each choice moving at most {args.step:g} of its range either way) x {len(motions)} "
        f"validation motions ({', '.join(m.name for m in motions)}): {d_sim.size} central differences of the "
        "tracking reward; truth: the Warp rollout of each perturbed design (whole motions)",
        f"- the critic on the unperturbed designs: Pearson r {level['base_pearson']:.2f} with their simulated rewards; "
        f"simulated change RMS {level['sim_rms']:.1f}, clear (|change| > {args.clear:g}) in {level['clear']} of "
        f"{level['triples']}",
        "",
        "| critic difference | Pearson r with the simulated | Spearman r | sign agrees (clear changes) | RMS |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['pearson']:.2f} | {r['spearman']:.2f} | {100 * r['sign']:.0f} % | {r['rms']:.1f} |"
        )
    emit(written=str(write_report(args.out, lines)))


if __name__ == "__main__":
    main()
