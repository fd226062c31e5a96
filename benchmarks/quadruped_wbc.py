"""Oracle whole-body controller (MuJoCo C + mink) on random quadruped designs x validation motions.

Writes benchmarks/results/quadruped_wbc.md: mean position / orientation error, survival,
falls, mean actuator torque and seconds per episode, for random designs and for the nominal
design (on the same motions and on the whole validation split, the reachability check of the
space's `motion_offset`). Usage:
    python benchmarks/quadruped_wbc.py [--designs 20] [--seed 0] [--workers 2]
        [--motions reach_place:100 wipe:101 hammer:102] [--set com_cost=1.0 ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from tt.baselines.evaluate import score_episode
from tt.report import markdown_table, summary_row
from tt.sim.designs import get_space
from tt.sim.motions import for_space, get_motion, motion_set
from tt.sim.validate import oracle_rollout
from tt.sim.wbc import WBCConfig

try:
    from machine import machine_header
except ImportError:  # run as a module from the repository root
    from benchmarks.machine import machine_header

SPACE = "quadruped"
DEFAULT_MOTIONS = ("reach_place:100", "wipe:101", "hammer:102")


def _evaluate_chunk(args):
    designs, motion_names, config = args
    motions = for_space([get_motion(name) for name in motion_names], SPACE)
    t = time.perf_counter()
    ep = oracle_rollout(designs, motions, wbc_config=config)
    seconds = time.perf_counter() - t
    _, metrics = score_episode(ep, designs, motions, "tracking_torque")
    metrics["fallen"] = ep.fallen.any(dim=1).double().numpy().reshape(len(designs), len(motions))
    return metrics, seconds


def _run(designs, motion_names, config, workers):
    """(D, M) metrics and CPU seconds; work split over designs, or over motions for one design."""
    by_motion = len(designs) == 1
    # Contiguous chunks, so that concatenating the results keeps the input order.
    if by_motion:
        jobs = [(designs, list(c), config) for c in np.array_split(np.array(motion_names, dtype=object), workers) if len(c)]
    else:
        jobs = [(list(c), motion_names, config) for c in np.array_split(np.array(designs, dtype=object), workers) if len(c)]
    with ProcessPoolExecutor(len(jobs)) as pool:
        results = list(pool.map(_evaluate_chunk, jobs))
    metrics = {k: np.concatenate([r[0][k] for r in results], axis=1 if by_motion else 0) for k in results[0][0]}
    return metrics, sum(r[1] for r in results)


def _row(name, metrics, seconds=None, episodes=None):
    row = {"name": name, **summary_row(metrics)}
    row["fallen_pct"] = 100.0 * float(np.mean(metrics["fallen"]))
    if seconds is not None:
        row["sec_per_episode"] = seconds / episodes
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--designs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--motions", nargs="+", default=list(DEFAULT_MOTIONS))
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="WBCConfig overrides")
    ap.add_argument("--no-nominal-val", action="store_true", help="skip the nominal design on the whole val split")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "quadruped_wbc.md")
    args = ap.parse_args()

    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        overrides[key] = type(getattr(WBCConfig(), key))(value)
    config = WBCConfig(**overrides)
    space = get_space(SPACE)
    designs = space.sample(args.designs, seed=args.seed)

    start = time.perf_counter()
    metrics, cpu = _run(designs, args.motions, config, args.workers)
    wall = time.perf_counter() - start
    nominal, nominal_cpu = _run([space.nominal()], args.motions, config, args.workers)
    rows = [
        _row(f"{args.designs} random designs", metrics, cpu, metrics["pos_err"].size),
        _row("nominal design", nominal, nominal_cpu, nominal["pos_err"].size),
    ]
    val_names = [m.name for m in motion_set("val", arms=1)]
    if not args.no_nominal_val:
        val, val_cpu = _run([space.nominal()], val_names, config, args.workers)
        rows.append(_row(f"nominal design, all {len(val_names)} val motions", val, val_cpu, val["pos_err"].size))

    cols = [("pos_err", "pos err (cm)"), ("orn_err", "orn err (deg)"), ("survival_pct", "survival (%)"),
            ("fallen_pct", "fell (%)"), ("torque", "torque |tau| (N m)"), ("sec_per_episode", "s / episode (1 core)")]
    table = markdown_table(rows, cols, first=("name", "run"))
    per_design = "\n".join(
        f"| {d} | " + " | ".join(f"{e:.1f}" for e in metrics["pos_err"][d]) + f" | {int(metrics['survival'][d].sum())}/{len(args.motions)} |"
        for d in range(len(designs))
    )
    changed = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
               if getattr(config, f.name) != f.default}
    text = (
        "# Oracle whole-body controller: MuJoCo C + mink on random quadruped designs\n\n"
        + machine_header("cpu")
        + f"- {args.designs} designs (seed {args.seed}) x motions {', '.join(args.motions)} (validation split, moved by "
        f"the space's motion_offset {tuple(space.motion_offset)}); {args.workers} worker processes, {wall:.0f} s wall\n"
        f"- WBCConfig: defaults{'' if not changed else ' except ' + repr(changed)}\n\n"
        + table + "\n\n"
        "Errors and torque average over the steps before termination (0.8 m summed position error, or a fall: "
        "base below half its standing height or tilted over 45 deg); survival is the share of episodes that "
        "track their whole motion, fell the share that ended in a fall.\n\n"
        "Position error [cm] per random design and motion:\n\n"
        "| design | " + " | ".join(args.motions) + " | survived |\n|" + "---|" * (len(args.motions) + 2) + "\n"
        + per_design + "\n"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
