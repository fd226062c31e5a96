"""How much of a critic's r on R2 hangs on telling failing pairs from tracking ones.

For a ladder result (`benchmarks/dit_ladder.py`'s JSON: predicted and simulated tracking
rewards of D held-out designs x M validation motions) it reports, beside the critic's own
pooled and within-motion r:

* the critic with the failures known: its predictions, set to 0 on the pairs that fail in
  simulation (reward below `dit_ladder.FAILED_BELOW`); the r a critic would reach that
  separated failures perfectly and kept its own ranking of the rest;
* the failure flag alone (1 for tracking, 0 for failing) as a predictor;
* the critic gated by the simulated start: its predictions, set to 0 where the episode's
  first record is more than `--gate` from the target (what one simulated control step,
  about 1 % of an episode, tells a critic);
* a kinematic reach test: for each design, the end-effector positions of `--configs`
  uniform random joint configurations (MuJoCo forward kinematics), and for each motion the
  largest distance from one of its first `--early` targets to the nearest such position;
  its AUC for failing pairs says how far failure is a question of reach alone.

Writes ``benchmarks/results/critic_failures.md``. Usage:
``python benchmarks/critic_failures.py RESULT.json [RESULT.json ...] [--configs 3000] [--early 10]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from dit_ladder import FAILED_BELOW  # noqa: E402
from machine import machine_header  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def auc(score_tracking: np.ndarray, score_failing: np.ndarray) -> float:
    """The chance that a tracking pair scores above a failing one (ties count half)."""
    a, b = np.ravel(score_tracking)[:, None], np.ravel(score_failing)[None, :]
    return float(np.mean((a > b) + 0.5 * (a == b)))


def reach_distance(space_name: str, designs, motions, configs: int, early: int, seed: int = 0) -> np.ndarray:
    """(D, M) [m]: per design and motion, the largest distance from one of the motion's first
    `early` end-effector targets to the nearest of `configs` sampled reachable positions."""
    import mujoco

    from tt.sim.designs import get_space

    space = get_space(space_name)
    site = space.ee_sites()[0]
    rng = np.random.default_rng(seed)
    out = np.zeros((len(designs), len(motions)))
    for i, design in enumerate(designs):
        model = space.model(design)
        data = mujoco.MjData(model)
        lo, hi = model.jnt_range[:, 0], model.jnt_range[:, 1]
        points = np.empty((configs, 3))
        for k in range(configs):
            data.qpos[:] = rng.uniform(lo, hi)
            mujoco.mj_kinematics(model, data)
            points[k] = data.site(site).xpos
        for j, motion in enumerate(motions):
            targets = np.asarray(motion.pos)[:early, 0]  # (early, 3)
            out[i, j] = np.linalg.norm(targets[:, None] - points[None], axis=-1).min(axis=1).max()
    return out


def start_errors(designs, motions) -> tuple[np.ndarray, np.ndarray]:
    """(D, M) [m] each: the end-effector position error at the first record of the simulated
    episode (the start posture, fifty IK steps from qpos0 toward the first target, after one
    control step) and the smallest error over the episode's executed steps."""
    import torch

    from tt.sim.rollout import rollout

    ep = rollout(designs, motions, device="cpu")
    err = torch.linalg.vector_norm(ep.ee_pos - ep.target_pos, dim=-1).sum(-1)  # (W, T)
    best = torch.where(ep.alive, err, torch.full_like(err, float("inf"))).min(dim=1).values
    best = torch.where(torch.isfinite(best), best, err[:, 0])
    shape = (len(designs), len(motions))
    return err[:, 0].numpy().reshape(shape), best.numpy().reshape(shape)


def main(argv: list[str] | None = None) -> None:
    from tt.ladder import heldout_designs, pearson, validation_motions, within_motion

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("results", nargs="+", type=Path)
    p.add_argument("--configs", type=int, default=3000, help="random joint configurations per design")
    p.add_argument("--early", type=int, default=10, help="a motion's first targets the reach test looks at")
    p.add_argument(
        "--gate",
        type=float,
        nargs="+",
        default=[0.2, 0.3, 0.4],
        help="start-posture error [m] past which the gated critic predicts 0",
    )
    p.add_argument("--out", type=Path, default=RESULTS / "critic_failures.md")
    args = p.parse_args(argv)
    results = [json.loads(path.read_text()) | {"file": path} for path in args.results]
    spaces = {(r["space"], r["designs"], tuple(r["motions"])) for r in results}
    if len(spaces) != 1:
        raise SystemExit(f"the results score different pairs: {sorted(spaces)}")
    space, count, names = spaces.pop()
    designs = heldout_designs(space, count)
    motions = validation_motions(space, len(names))
    if tuple(m.name for m in motions) != names:
        raise SystemExit(f"validation motions {[m.name for m in motions]} are not the results' {list(names)}")
    simulated = np.asarray(results[0]["simulated"], float)
    failed = simulated < FAILED_BELOW
    reach = reach_distance(space, designs, motions, args.configs, args.early)
    start, closest = start_errors(designs, motions)
    flag = (~failed).astype(float)
    rows = []
    spread = 0.0
    for r in results:
        # Each result against its own simulation: runs on other CPUs may differ by round-off.
        pred, sim = np.asarray(r["predicted"], float), np.asarray(r["simulated"], float)
        spread = max(spread, float(np.abs(sim - simulated).max()))
        fail = sim < FAILED_BELOW
        known = np.where(fail, 0.0, pred)
        rows.append(
            f"| `{r['file'].parent.name}/{r['file'].name}` | {pearson(pred, sim):.2f} / "
            f"{np.nanmean(within_motion(pred, sim)):.2f} | {auc(pred[~fail], pred[fail]):.2f} | "
            f"{pearson(known, sim):.2f} / {np.nanmean(within_motion(known, sim)):.2f} | "
            + " | ".join(
                f"{pearson(g, sim):.2f} / {np.nanmean(within_motion(g, sim)):.2f}"
                for g in (np.where(start > cut, 0.0, pred) for cut in args.gate)
            )
            + " |"
        )
    lines = [
        "# R2: how much of the critic's r is telling failing pairs from tracking ones",
        "",
        machine_header(),
        "",
        f"- command: `python benchmarks/critic_failures.py {' '.join(str(p) for p in args.results)} "
        f"--configs {args.configs} --early {args.early} --gate {' '.join(f'{g:g}' for g in args.gate)}`",
        f"- pairs: {count} held-out `{space}` designs x {len(names)} validation motions ({', '.join(names)}); "
        f"failing: simulated tracking reward below {FAILED_BELOW:g}: {failed.mean():.0%} of pairs; "
        f"{int(failed.all(axis=1).sum())} designs fail on every motion, {int((~failed).all(axis=1).sum())} on none",
        "",
        "| result | critic: pooled / within-motion r | critic's AUC for failing pairs | critic with the "
        "failures known: "
        "pooled / within-motion r | "
        + " | ".join(f"critic gated at {cut * 100:g} cm: pooled / within-motion r" for cut in args.gate)
        + " |",
        "|---|---|---:|---|" + "---|" * len(args.gate),
        *rows,
        "",
        "- gated: the critic's prediction set to 0 where the simulated start (the episode's first record) is more "
        "than the gate from the target. The gates were not chosen on other designs: they bracket the medians "
        "below, measured on these same pairs, so the gated columns say what a start-aware critic could reach, "
        "not what a tuned rule would on new designs.",
        f"- each row against its own run's simulation (largest difference from the first's: {spread:.3g}; the "
        "flag and reach lines use the first's)",
        f"- the failure flag alone as a predictor: pooled r {pearson(flag, simulated):.2f}, within-motion "
        f"{np.nanmean(within_motion(flag, simulated)):.2f}",
        f"- kinematic reach ({args.configs} random joint configurations per design, the motion's first {args.early} "
        f"targets): AUC for failing pairs {auc(-reach[~failed], -reach[failed]):.2f}; median largest distance "
        f"{np.median(reach[failed]) * 100:.0f} cm for failing pairs, {np.median(reach[~failed]) * 100:.0f} cm for "
        f"tracking ones; pooled r of minus the distance with the reward {pearson(-reach, simulated):.2f}",
        f"- the start posture (the simulated episode's first record, after the start-posture IK and one control "
        f"step): AUC of minus its position error for failing pairs {auc(-start[~failed], -start[failed]):.2f}; "
        f"median error {np.median(start[failed]) * 100:.0f} cm for failing pairs, "
        f"{np.median(start[~failed]) * 100:.0f} "
        f"cm for tracking ones; {np.mean(start[failed] > 0.1):.0%} of failing pairs and "
        f"{np.mean(start[~failed] > 0.1):.0%} of tracking ones start more than 10 cm from the target",
        f"- the closest a failing pair's end effector comes to its target while the episode runs: median "
        f"{np.median(closest[failed]) * 100:.0f} cm (tracking pairs: {np.median(closest[~failed]) * 100:.0f} cm)",
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
