"""Oracle (MuJoCo C + mink DiffIK) on random ViperX designs x the validation motions.

Writes benchmarks/results/oracle.md: mean position / orientation error, survival and
seconds per episode, next to the paper's Random row. Usage:
    python benchmarks/oracle.py [--designs 100] [--seed 0] [--workers 2]
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from tt.baselines.evaluate import evaluate_designs
from tt.report import markdown_table, summary_row
from tt.sim.designs import get_space
from tt.sim.motions import motion_set

try:
    from machine import machine_header
except ImportError:  # run as a module from the repository root
    from benchmarks.machine import machine_header

PAPER_RANDOM = {
    "name": "paper: Random (ViperX, single trajectory)",
    "pos_err": 19.4,
    "orn_err": 8.9,
    "survival_pct": 72.2,
}


def _evaluate_chunk(args):
    designs, seed_split = args
    motions = motion_set("val", arms=1)
    t = time.perf_counter()
    ev = evaluate_designs(designs, motions, "tracking", backend="mujoco")
    return ev.metrics, time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--designs", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "oracle.md")
    args = ap.parse_args()

    space = get_space("viperx")
    designs = space.sample(args.designs, seed=args.seed)
    motions = motion_set("val", arms=1)
    chunks = [designs[i :: args.workers] for i in range(args.workers)]
    start = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(_evaluate_chunk, [(c, args.seed) for c in chunks]))
    wall = time.perf_counter() - start
    metrics = {k: np.concatenate([r[0][k] for r in results]) for k in results[0][0]}
    cpu_seconds = sum(r[1] for r in results)
    episodes = len(designs) * len(motions)

    nominal = evaluate_designs([space.nominal()], motions, "tracking", backend="mujoco").metrics
    rows = [
        {
            "name": f"tt oracle: {args.designs} random ViperX designs",
            **summary_row(metrics),
            "sec_per_episode": cpu_seconds / episodes,
        },
        {"name": "tt oracle: nominal ViperX", **summary_row(nominal)},
        PAPER_RANDOM,
    ]
    cols = [
        ("pos_err", "pos err (cm)"),
        ("orn_err", "orn err (deg)"),
        ("survival_pct", "survival (%)"),
        ("sec_per_episode", "s / episode (1 core)"),
    ]
    table = markdown_table(rows, cols, first=("name", "run"))
    steps = float(np.mean([m.steps for m in motions]))
    text = (
        "# Oracle: MuJoCo C + mink DiffIK on random ViperX designs\n\n"
        + machine_header("cpu")
        + f"- {args.designs} designs (seed {args.seed}) x {len(motions)} validation motions = {episodes} episodes "
        f"(mean {steps:.0f} control steps, 10 physics steps each); {args.workers} worker processes, "
        f"{wall:.0f} s wall\n\n" + table + "\n\n"
        "Errors average over the steps before termination (50 cm), survival is the share of episodes "
        "that track their whole motion. The paper's numbers come from its own design-space sampling "
        "and motions, so they are for orientation, not a like-for-like comparison.\n"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
