"""Random quadruped designs on the validation motions, and mjwarp vs the oracle in world-steps/s.

Two parts, one report (benchmarks/results/quadruped.md):

* quality: D random designs of the quadruped space (seed 0) x the 30 single-arm validation
  motions (moved by the space's ``motion_offset``), run on the oracle (MuJoCo C + mink
  whole-body controller, `tt.sim.validate.oracle_rollout`) in worker processes, one design
  per job. Mean position / orientation error, survival, falls, actuator torque, next to the
  paper's Random row for the quadruped (single trajectory), with the nominal design on the
  same motions and a breakdown by discrete choice. ``--motions-per-design K`` gives each
  design K of the motions instead of all of them (design d gets motions d*K .. d*K+K-1,
  modulo 30, so every motion gets the same number of designs).
* speed: closed-loop world-steps per second of the ``mjwarp`` backend (MuJoCo-Warp physics
  with tt's batched whole-body controller kernel, and for reference with the oracle's mink
  controller on the host) and of the oracle on the same designs and the same short motion,
  in this process, before the quality part starts its workers. A world-step
  is one physics step (0.002 s) of one world, controller included; both are timed warm
  (after a 2-step run of the same designs), the best of ``--speed-repeats`` runs each with
  the backends alternating, per wall second and per CPU second of the process; their
  episodes are compared (largest end-effector difference).

Prints one JSON line per measurement (one per design in the quality part: the progress log).
``--budget-min`` bounds the quality part on a slow or shared machine: no design starts after
that many minutes, and the report covers the designs done and says so. ``--set`` runs the
quality part with `WBCConfig` overrides (how the controller's weights were tuned) and
``--motions`` on chosen library motions.
Usage:
    python benchmarks/quadruped.py [--designs 100] [--seed 0] [--workers 2] [--budget-min M]
        [--motions NAME:SEED ...] [--motions-per-design 0] [--set FIELD=VALUE ...]
        [--speed-sizes 1 16 64 256] [--speed-mixed 4] [--speed-steps 50] [--speed-repeats 2]
        [--skip-speed] [--skip-quality] [--raw RAW.json] [--resume RAW.json] [--from-raw RAW.json ...]
        [--out benchmarks/results/quadruped.md]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from itertools import islice
from pathlib import Path

import numpy as np

try:
    from machine import machine_header
except ImportError:  # run as a module from the repository root
    from benchmarks.machine import machine_header

SPACE = "quadruped"
#: The paper's Random row, quadruped, single trajectory (appendix, tracking-only table).
PAPER_RANDOM = {
    "name": "paper: Random (quadruped, single trajectory)",
    "pos_err": 3.4,
    "orn_err": 8.4,
    "survival_pct": 96.1,
}
METRICS = ("pos_err", "orn_err", "survival", "torque", "reward", "length")


def _log(record: dict) -> None:
    print(json.dumps(record), flush=True)


def _val_motions(names: list[str] | None = None):
    """Motions by library name (``reach_place:100``), default the 30 single-arm validation
    motions, placed for the quadruped (the space's ``motion_offset``)."""
    from tt.sim.motions import for_space, motion_set, resolve_motion

    return for_space([resolve_motion(n) for n in names] if names else motion_set("val", arms=1), SPACE)


def _short(motion, steps: int):
    from tt.sim.motions.base import Motion

    return Motion(f"{motion.name}[:{steps}]", motion.pos[:steps], motion.quat[:steps], motion.dt)


# ------------------------------------------------------------------------------ quality
def _evaluate_design(job: tuple) -> dict:
    """Oracle episodes of one design on its motions: per-motion metrics, falls and seconds."""
    from tt.baselines.evaluate import score_episode
    from tt.sim.validate import oracle_rollout
    from tt.sim.wbc import WBCConfig

    index, design, motion_ids, names, overrides = job
    motions = [_val_motions(names)[m] for m in motion_ids]
    start = time.perf_counter()
    ep = oracle_rollout([design], motions, wbc_config=WBCConfig(**overrides))
    seconds = time.perf_counter() - start
    _, metrics = score_episode(ep, [design], motions, "tracking")
    out = {k: metrics[k][0].tolist() for k in METRICS}
    out.update(index=index, motions=list(motion_ids), fell=ep.fallen.any(dim=1).tolist(), seconds=seconds)
    return out


def _assignments(designs: int, motions: int, per_design: int) -> list[list[int]]:
    if per_design <= 0 or per_design >= motions:
        return [list(range(motions)) for _ in range(designs)]
    return [[(d * per_design + j) % motions for j in range(per_design)] for d in range(designs)]


def run_quality(
    designs,
    assignments,
    workers: int,
    budget_s: float | None = None,
    *,
    motion_names: list[str] | None = None,
    overrides: dict | None = None,
    skip: set[int] = frozenset(),
) -> list[dict]:
    """Episodes of the designs, in design order; logs one JSON line per finished design.

    assignments: indices into the motions (`_val_motions(motion_names)`) per design.
    budget_s: stop starting designs once this many seconds have passed; the designs started
    by then finish, so the result is the first k designs not skipped.
    overrides: `WBCConfig` fields that differ from the defaults.
    skip: design indices already measured (a resumed run); they are not run or returned."""
    jobs = iter(
        [
            (i, d, a, motion_names, overrides or {})
            for i, (d, a) in enumerate(zip(designs, assignments))
            if i not in skip
        ]
    )
    todo = len(designs) - len(skip)
    results: dict[int, dict] = {}
    start = time.perf_counter()
    # spawn, not fork: the speed part has started torch's and Warp's thread pools in this
    # process, and a forked child that inherits them deadlocks on its first parallel op.
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        running = {pool.submit(_evaluate_design, job) for job in islice(jobs, workers)}
        while running:
            done, running = wait(running, return_when=FIRST_COMPLETED)
            for fut in done:
                r = fut.result()
                results[r["index"]] = r
                elapsed = time.perf_counter() - start
                _log(
                    {
                        "part": "quality",
                        "design": r["index"],
                        "done": len(results),
                        "of": todo,
                        "pos_err_cm": float(np.nanmean(r["pos_err"])),
                        "survived": int(np.sum(r["survival"])),
                        "episodes": len(r["motions"]),
                        "seconds": round(r["seconds"], 1),
                        "elapsed_s": round(elapsed, 1),
                        "eta_s": round(elapsed / len(results) * (todo - len(results)), 1),
                    }
                )
                if budget_s is None or elapsed < budget_s:
                    running |= {pool.submit(_evaluate_design, job) for job in islice(jobs, 1)}
    return [results[i] for i in sorted(results)]


def _flat(results: list[dict], key: str) -> np.ndarray:
    return np.concatenate([np.asarray(r[key], dtype=np.float64) for r in results])


def _summary(results: list[dict], name: str) -> dict:
    """The paper's aggregation: errors and torque averaged over episodes (each over its counted
    steps), survival and falls as shares of episodes."""
    row = {"name": name, "episodes": int(sum(len(r["motions"]) for r in results))}
    for key in ("pos_err", "orn_err", "torque", "reward"):
        v = _flat(results, key)
        row[key] = float(np.mean(v[np.isfinite(v)])) if np.isfinite(v).any() else float("nan")
    row["survival_pct"] = 100.0 * float(np.mean(_flat(results, "survival")))
    row["fallen_pct"] = 100.0 * float(np.mean(_flat(results, "fell")))
    row["sec_per_episode"] = sum(r["seconds"] for r in results) / row["episodes"]
    return row


def _fmt(v, digits: int = 1) -> str:
    if isinstance(v, str):
        return v
    if v is None or not np.isfinite(v):
        return "-"
    return f"{v:.{digits}f}"


# ------------------------------------------------------------------------------ speed
#: The closed-loop rollouts the speed part times: name -> (label, runner(designs, motion)).
SPEED_RUNS = ("oracle", "mjwarp", "mjwarp_mink")
SPEED_LABELS = {
    "oracle": "oracle (MuJoCo C + mink)",
    "mjwarp": "mjwarp (batched WBC kernel)",
    "mjwarp_mink": "mjwarp (mink WBC on the host)",
}


def _speed_runner(name: str, designs):
    from tt.sim.mjwarp_backend import mjwarp_rollout
    from tt.sim.rollout import rollout
    from tt.sim.validate import oracle_rollout

    if name == "oracle":
        return lambda m: oracle_rollout(designs, [m])
    if name == "mjwarp":  # the backend as `tt.sim.rollout.rollout` runs it
        return lambda m: rollout(designs, [m], backend="mjwarp", device="cpu")
    return lambda m: mjwarp_rollout(designs, [m], device="cpu", floating_controller="mink")


def _timed(designs, motion, repeats: int) -> dict:
    """Warm closed-loop wall and CPU seconds of each of `SPEED_RUNS` on `designs` x `motion`:
    the best of `repeats` runs each, the runs alternating so that all see the same share of
    a busy machine."""
    from tt.sim.designs import get_space
    from tt.sim.wbc import WBCConfig

    runs = {name: _speed_runner(name, designs) for name in SPEED_RUNS}
    warm = _short(motion, 2)
    for run in runs.values():
        run(warm)  # mjwarp: compiles (or loads) the Warp modules
    wall = {k: [] for k in runs}
    cpu = {k: [] for k in runs}
    episodes = {}
    for _ in range(repeats):
        for name, run in runs.items():
            t, c = time.perf_counter(), time.process_time()
            episodes[name] = run(motion)
            wall[name].append(time.perf_counter() - t)
            cpu[name].append(time.process_time() - c)

    model = get_space(SPACE).model(designs[0])
    world_steps = len(designs) * motion.steps * WBCConfig().substeps(model)
    ref = episodes["oracle"]
    out = {"worlds": len(designs), "control_steps": motion.steps, "world_steps": world_steps, "repeats": repeats}
    for name in runs:
        ep = episodes[name]
        out[name] = {
            "s": min(wall[name]),
            "cpu_s": min(cpu[name]),
            "wsps": world_steps / min(wall[name]),
            "wsps_cpu": world_steps / min(cpu[name]),
            "alive": int(ep.alive.cpu().sum()),
            "max_ee_diff_mm": 1000.0 * (ep.ee_pos.cpu() - ref.ee_pos).abs().max().item(),
        }
    return out


def run_speed(space, sample, sizes: list[int], mixed: int, steps: int, repeats: int) -> list[dict]:
    """One structure (the nominal discrete choice with the sampled designs' continuous values)
    at each size in `sizes`, then `mixed` random designs of their own discrete choices."""
    from tt.sim.designs import Design

    motion = _short(_val_motions()[0], steps)
    nominal = space.nominal()
    rows = []
    for n in sizes:
        designs = [Design(SPACE, nominal.discrete, d.continuous) for d in sample[:n]]
        r = {"case": f"one structure, N = {n}", "motion": motion.name, **_timed(designs, motion, repeats)}
        _log({"part": "speed", **r})
        rows.append(r)
    if mixed > 0:
        designs = sample[:mixed]
        r = {
            "case": f"{mixed} random designs ({len({d.discrete for d in designs})} structures)",
            "motion": motion.name,
            **_timed(designs, motion, repeats),
        }
        _log({"part": "speed", **r})
        rows.append(r)
    return rows


def _comparison(random_row: dict, failed: list) -> str:
    """What the random designs' row says next to the paper's Random row."""
    p = PAPER_RANDOM
    ended = "none fell or left the target by more than 0.8 m" if not failed else f"{len(failed)} episodes ended early"
    return (
        f"tt's random designs track at {random_row['pos_err']:.2f} cm / {random_row['orn_err']:.1f} deg against "
        f"the paper's Random {p['pos_err']} cm / {p['orn_err']} deg, and {ended} (survival "
        f"{random_row['survival_pct']:.1f} % against {p['survival_pct']} %). Two differences that plausibly make "
        "tt's task easier, not measured here: tt's oracle holds the feet on their stance points and moves only "
        "the base and the arm, where the paper runs learned (RL) whole-body controllers, and the motions "
        "are placed into the quadruped's workspace by the space's motion_offset.\n"
    )


def _speed_summary(speed: list[dict]) -> str:
    """A sentence on the CPU-time rates: the oracle's range, and mjwarp's from its best case to
    the mixed designs'."""
    oracle = [r["oracle"]["wsps_cpu"] for r in speed]
    ratio = {r["case"]: r["mjwarp"]["wsps_cpu"] / r["oracle"]["wsps_cpu"] for r in speed}
    best = max(ratio, key=ratio.get)
    text = (
        f"Per CPU second the oracle runs {_si(min(oracle))} to {_si(max(oracle))} world-steps whatever the batch "
        f"(one world after another); mjwarp's best is {ratio[best]:.2f}x the oracle, at {best}"
    )
    mixed = [r for r in speed if "random" in r["case"]]
    if mixed:
        text += (
            f", and {ratio[mixed[0]['case']]:.2f}x for {mixed[0]['case']}: random quadruped designs rarely "
            "share a structure (7 binary choices, 128 structures), and every structure group is a batch of "
            "its own"
        )
    faster = "mjwarp" if ratio[best] > 1.0 else "the oracle"
    return text + f". On this CPU {faster} is the faster way to roll out the quadruped at these batch sizes.\n"


def _si(x: float) -> str:
    return f"{x / 1e3:.1f} k" if x >= 1e3 else f"{x:.0f}"


# ------------------------------------------------------------------------------ report
def _part_line(name: str, meta: dict) -> str:
    """Header line of one part: when, the command, wall time and the machine's load."""
    cores = os.cpu_count() or 1
    busy = max(meta["load_start"][0], meta["load_end"][0]) > cores
    load = (
        f"load average (1, 5, 15 min) {', '.join(f'{x:.1f}' for x in meta['load_start'])} at the start, "
        f"{', '.join(f'{x:.1f}' for x in meta['load_end'])} at the end on {cores} cores"
    )
    commands = " and ".join(
        f"`python benchmarks/quadruped.py {' '.join(argv)}`" for argv in meta.get("commands", [meta.get("argv")])
    )
    return f"- {name}: {meta['date']}, {commands}, {meta['wall'] / 60:.0f} min wall; {load}" + (
        ": other jobs shared the machine, so times are upper bounds and wall-clock rates lower bounds" if busy else ""
    )


def _quality_lines(args, space, motions, results, nominal_results) -> list[str]:
    """The report's section on the random designs' tracking."""
    from tt.report import markdown_table

    episodes = sum(len(r["motions"]) for r in results)
    all_motions = len({m for r in results for m in r["motions"]}) == len(motions) and episodes == len(results) * len(
        motions
    )
    runs = [sum(m == j for r in results for m in r["motions"]) for j in range(len(motions))]
    runs_text = str(min(runs)) if min(runs) == max(runs) else f"{min(runs)} to {max(runs)}"
    which = "validation motions" if not args.motions else "motions " + ", ".join(args.motions)
    coverage = (
        f"x all {len(motions)} {which}"
        if all_motions
        else f"x {args.motions_per_design} of the {len(motions)} {which} each (each motion run by {runs_text} designs)"
    )
    budget_note = ""
    if len(results) < args.designs:
        budget_note = (
            f" These are the first {len(results)} of the {args.designs} designs asked for (seed {args.seed}): "
            f"the quality part's time budget (`--budget-min {args.budget_min:g}`) on the shared 2 cores "
            "ended the sampling there."
        )
    rows = [
        _summary(results, f"tt oracle: {len(results)} random designs"),
        _summary(nominal_results, "tt oracle: nominal design"),
        PAPER_RANDOM,
    ]
    cols = [
        ("pos_err", "pos err (cm)"),
        ("orn_err", "orn err (deg)"),
        ("survival_pct", "survival (%)"),
        ("fallen_pct", "fell (%)"),
        ("torque", "torque (N m)"),
        ("reward", "reward"),
        ("episodes", "episodes"),
        ("sec_per_episode", "s / episode (wall, 1 worker)"),
    ]
    table = markdown_table(rows, cols, first=("name", "run"))

    per_design = np.array([np.nanmean(r["pos_err"]) for r in results])
    survived = np.array([np.mean(r["survival"]) for r in results])
    pct = np.percentile(per_design, [10, 50, 90])
    worst = np.argsort(-per_design)[:5]
    failed = [
        (r["index"], motions[m].name, bool(f))
        for r in results
        for m, s, f in zip(r["motions"], r["survival"], r["fell"])
        if s < 1
    ]

    # Mean per-design error by each binary choice: which choices random sampling pays for.
    by_choice = [
        "| choice | value 0 | pos err (cm) | survival (%) | value 1 | pos err (cm) | survival (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    params = space.discrete_params(space.nominal().discrete)
    for k, p in enumerate(params):
        cells = []
        for v in (0, 1):
            sel = [i for i, r in enumerate(results) if args.sample[r["index"]].discrete[k] == v]
            cells += [
                f"{p.options[v]} ({len(sel)})",
                _fmt(float(np.mean(per_design[sel])) if sel else float("nan"), 2),
                _fmt(100.0 * float(np.mean(survived[sel])) if sel else float("nan")),
            ]
        by_choice.append(f"| {p.name} | " + " | ".join(cells) + " |")

    per_motion = ["| motion | steps | pos err (cm) | orn err (deg) | survival (%) |", "|---|---|---|---|---|"]
    for j, m in enumerate(motions):
        pe = [r["pos_err"][i] for r in results for i, mm in enumerate(r["motions"]) if mm == j]
        oe = [r["orn_err"][i] for r in results for i, mm in enumerate(r["motions"]) if mm == j]
        sv = [r["survival"][i] for r in results for i, mm in enumerate(r["motions"]) if mm == j]
        if not sv:
            continue
        per_motion.append(
            f"| {m.name} | {m.steps} | {_fmt(float(np.nanmean(pe)), 2)} | {_fmt(float(np.nanmean(oe)))} | "
            f"{_fmt(100.0 * float(np.mean(sv)))} |"
        )

    return [
        "## Tracking of random designs (oracle: MuJoCo C + mink whole-body controller)\n",
        f"{len(results)} random quadruped designs (seed {args.seed}) {coverage} = {episodes} episodes, moved by the "
        f"space's motion_offset {tuple(space.motion_offset)}; reward `tracking`; {args.workers} worker processes; "
        f"WBCConfig: {'defaults' if not args.overrides else 'defaults except ' + repr(args.overrides)}."
        f"{budget_note}\n",
        table,
        "",
        "Errors, torque (|tau|_2 over the actuators [N m]) and reward average over each episode's counted steps, "
        "then over episodes; survival is the share of episodes that track their whole motion; fell the share "
        "that ended in a fall. An episode ends at the first step whose position error exceeds 0.8 m or where "
        "the robot has fallen (base below half its standing height, or tilted more than 45 deg), as in the "
        "paper for the quadruped (`tt.sim.wbc.WBCConfig`, `tt.sim.validate`). The paper's numbers come from "
        "its own RL whole-body controllers, design sampling and motions: they are for orientation, not a "
        "like-for-like comparison (tt's oracle controller is a stance-holding differential IK that never "
        "steps, see `tt.sim.wbc`).\n",
        _comparison(rows[0], failed),
        f"Per-design mean position error [cm]: 10th / 50th / 90th percentile {pct[0]:.2f} / {pct[1]:.2f} / "
        f"{pct[2]:.2f}; worst designs: " + ", ".join(f"#{i} {per_design[i]:.1f}" for i in worst) + ".",
        f"Episodes that did not survive: {len(failed)}"
        + (
            ""
            if not failed
            else " ("
            + "; ".join(f"design #{d} on {m}: {'fell' if f else 'error > 0.8 m'}" for d, m, f in failed[:12])
            + ("; ..." if len(failed) > 12 else "")
            + ")"
        )
        + ".\n",
        "### By discrete choice (number of designs in brackets; per-design means)\n",
        "\n".join(by_choice),
        "",
        "### By motion (all designs that ran it)\n",
        "\n".join(per_motion),
        "",
    ]


def _speed_lines(speed: list[dict]) -> list[str]:
    """The report's section on closed-loop speed."""
    labels = [SPEED_LABELS[k] for k in SPEED_RUNS]
    cpu_rows = [
        "| case | worlds | " + " | ".join(labels) + " | mjwarp / oracle |",
        "|---|---|" + "---|" * (len(labels) + 1),
    ]
    wall_rows = [
        "| case | worlds | "
        + " | ".join(f"{x} (s)" for x in labels)
        + " | "
        + " | ".join(f"{x} (world-steps/s)" for x in labels)
        + " |",
        "|---|---|" + "---|" * (2 * len(labels)),
    ]
    for r in speed:
        cpu_rows.append(
            f"| {r['case']} | {r['worlds']} | "
            + " | ".join(_si(r[k]["wsps_cpu"]) for k in SPEED_RUNS)
            + f" | {r['mjwarp']['wsps_cpu'] / r['oracle']['wsps_cpu']:.2f}x |"
        )
        wall_rows.append(
            f"| {r['case']} | {r['worlds']} | "
            + " | ".join(f"{r[k]['s']:.2f}" for k in SPEED_RUNS)
            + " | "
            + " | ".join(_si(r[k]["wsps"]) for k in SPEED_RUNS)
            + " |"
        )
    diff = max(r[k]["max_ee_diff_mm"] for r in speed for k in SPEED_RUNS)
    same_alive = all(r[k]["alive"] == r["oracle"]["alive"] for r in speed for k in SPEED_RUNS)
    steps = speed[0]["control_steps"]
    most = max(r["repeats"] for r in speed)
    fewer = [f"{r['repeats']} at {r['case']}" for r in speed if r["repeats"] != most]
    repeats = f"{most} timed runs each" + (f" ({', '.join(fewer)})" if fewer else "")
    return [
        "## Closed-loop speed: mjwarp vs the oracle (Warp device: cpu)\n",
        f"Same designs, same motion ({speed[0]['motion']}: {steps} control steps, "
        f"{steps * 10} physics steps of 0.002 s per world), in one process; warm (after a 2-step call of "
        f"each on the same designs, so Warp's modules are compiled or loaded); the best of {repeats}, "
        "the runs alternating. A world-step is one physics step "
        "of one world, the whole-body controller at 50 Hz included; each timed call includes its setup "
        "(models, controllers, start postures), as a caller pays it. mjwarp runs MuJoCo-Warp's physics with "
        "tt's batched whole-body controller kernel (`tt.kernels.wbc`, the backend's default) or, as a "
        "reference, with the oracle's mink controller on the host world by world. 'one structure': designs "
        "that share the nominal discrete choice (one `mjw.Model` with per-world numbers), continuous values "
        "from the random sample; the mixed case: the first random designs, each its own structure group "
        "(one batch after another).\n",
        "World-steps per CPU second of the process (every path runs on one thread here: MuJoCo C, mink "
        "and Warp's CPU kernels), the measure least disturbed by other jobs:\n",
        "\n".join(cpu_rows),
        "",
        "Wall-clock seconds and world-steps per second:\n",
        "\n".join(wall_rows),
        "",
        _speed_summary(speed),
        f"Every run kept every world alive for the whole motion: {'yes' if same_alive else 'no'}; the largest "
        f"end-effector difference from the oracle's episodes was {diff:.4f} mm (MuJoCo-Warp's float32 "
        "physics against MuJoCo C's float64), a check that all did the same work.\n",
    ]


def _merged_meta(a: dict, b: dict) -> dict:
    """One header entry for a part measured in two runs: both dates and commands, the summed
    wall time, the higher loads."""

    def commands(m: dict) -> list:
        return m["commands"] if "commands" in m else [m["argv"]]

    return {
        "date": f"{a['date']} and {b['date']}",
        "commands": commands(a) + commands(b),
        "wall": a["wall"] + b["wall"],
        "load_start": [max(x, y) for x, y in zip(a["load_start"], b["load_start"])],
        "load_end": [max(x, y) for x, y in zip(a["load_end"], b["load_end"])],
    }


def _report(args, space, motions, results, nominal_results, speed, meta: dict) -> str:
    """The markdown report: header (machine, and when and how each part ran), then each part."""
    lines = [
        "# Quadruped: random designs on the oracle, and mjwarp vs the oracle in world-steps/s\n",
        machine_header("cpu").rstrip("\n"),
        *[_part_line(f"{name} part", meta[name]) for name in ("quality", "speed") if name in meta],
        "",
    ]
    if results:
        lines += _quality_lines(args, space, motions, results, nominal_results)
    if speed:
        lines += _speed_lines(speed)
    return "\n".join(lines)


def _resumed(args) -> tuple[list[dict], list[dict], dict]:
    """The quality results, nominal runs and quality-part header of ``args.resume``, after
    checking that it measured the same designs on the same motions with the same controller."""
    raw = json.loads(args.resume.read_text())
    for name in ("seed", "motions", "motions_per_design", "overrides"):
        if raw["args"].get(name) != getattr(args, name):
            raise SystemExit(
                f"--resume {args.resume}: it ran with {name}={raw['args'].get(name)!r}, "
                f"this run has {name}={getattr(args, name)!r}"
            )
    results = [r for r in raw["results"] if r["index"] < args.designs]
    return results, raw["nominal"], raw["meta"]["quality"]


def main() -> None:
    import sys

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--designs", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--motions",
        nargs="+",
        default=None,
        metavar="NAME",
        help="library motions (NAME:SEED) instead of the 30 validation motions",
    )
    ap.add_argument("--motions-per-design", type=int, default=0, help="0: every motion")
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="FIELD=VALUE",
        help="WBCConfig overrides for the quality part, e.g. com_cost=1.0 (tuning the controller)",
    )
    ap.add_argument("--speed-sizes", type=int, nargs="*", default=[1, 16, 64, 256])
    ap.add_argument("--speed-mixed", type=int, default=4, help="random designs of mixed structures in the speed part")
    ap.add_argument("--speed-steps", type=int, default=50, help="control steps of the speed part's motion")
    ap.add_argument("--speed-repeats", type=int, default=2, help="timed runs per backend and case (best kept)")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-quality", action="store_true")
    ap.add_argument(
        "--budget-min",
        type=float,
        default=None,
        help="start no new design after this many minutes of the quality part; report the designs done",
    )
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "quadruped.md")
    ap.add_argument("--raw", type=Path, default=None, help="also save the measurements as JSON here")
    ap.add_argument(
        "--resume",
        type=Path,
        default=None,
        metavar="RAW.json",
        help="a --raw file of an earlier run with the same seed, designs and motions: keep its quality "
        "results (and nominal runs) and run only the designs it lacks",
    )
    ap.add_argument(
        "--from-raw",
        type=Path,
        nargs="+",
        default=None,
        help="write the report from --raw files (each file's parts replace earlier ones); run nothing",
    )
    args = ap.parse_args()
    args.argv = sys.argv[1:]

    from tt.sim.designs import get_space
    from tt.sim.wbc import WBCConfig

    space = get_space(SPACE)
    defaults = WBCConfig()
    args.overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if not hasattr(defaults, key):
            ap.error(f"--set {item}: WBCConfig has no field {key!r}")
        args.overrides[key] = type(getattr(defaults, key))(value)
    kept = (
        "seed",
        "designs",
        "workers",
        "motions",
        "motions_per_design",
        "overrides",
        "speed_sizes",
        "speed_mixed",
        "speed_steps",
        "budget_min",
    )
    if args.from_raw:
        # Parts from several runs: a file's quality part replaces an earlier one, its speed cases
        # join the earlier ones (replacing a case of the same name); the quality part's arguments
        # (seed, designs, motions) are the report's.
        results, nominal, meta = [], [], {}
        cases: dict[str, dict] = {}
        for path in args.from_raw:
            raw = json.loads(path.read_text())
            if raw["speed"] and "speed" in meta:
                meta["speed"] = _merged_meta(meta["speed"], raw["meta"]["speed"])
                raw["meta"].pop("speed")
            meta.update(raw["meta"])
            cases.update({r["case"]: r for r in raw["speed"]})
            if raw["results"]:
                results, nominal = raw["results"], raw["nominal"]
                for name in kept:
                    setattr(args, name, raw["args"][name])
        speed = sorted(cases.values(), key=lambda r: ("random" in r["case"], r["worlds"]))
        motions = _val_motions(args.motions)
        args.sample = space.sample(max(args.designs, *args.speed_sizes, args.speed_mixed), seed=args.seed)
    else:
        motions = _val_motions(args.motions)
        args.sample = space.sample(max(args.designs, *args.speed_sizes, args.speed_mixed), seed=args.seed)
        results, nominal, speed, meta = [], [], [], {}

        def part(name: str, run):
            start, load = time.perf_counter(), os.getloadavg()
            out = run()
            meta[name] = {
                "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                "argv": args.argv,
                "wall": time.perf_counter() - start,
                "load_start": load,
                "load_end": os.getloadavg(),
            }
            return out

        if not args.skip_speed:
            speed = part(
                "speed",
                lambda: run_speed(
                    space, args.sample, args.speed_sizes, args.speed_mixed, args.speed_steps, args.speed_repeats
                ),
            )
        if not args.skip_quality:
            designs = args.sample[: args.designs]
            earlier, nominal_earlier, meta_earlier = _resumed(args) if args.resume else ([], [], None)
            results, nominal = part(
                "quality",
                lambda: (
                    run_quality(
                        designs,
                        _assignments(len(designs), len(motions), args.motions_per_design),
                        args.workers,
                        None if args.budget_min is None else 60.0 * args.budget_min,
                        motion_names=args.motions,
                        overrides=args.overrides,
                        skip={r["index"] for r in earlier},
                    ),
                    nominal_earlier
                    or run_quality(
                        [space.nominal()],
                        _assignments(1, len(motions), 0),
                        args.workers,
                        motion_names=args.motions,
                        overrides=args.overrides,
                    ),
                ),
            )
            if args.resume:
                results = sorted(earlier + results, key=lambda r: r["index"])
                meta["quality"] = _merged_meta(meta_earlier, meta["quality"])
        if args.raw is not None:
            args.raw.write_text(
                json.dumps(
                    {
                        "args": {k: getattr(args, k) for k in kept},
                        "meta": meta,
                        "speed": speed,
                        "results": results,
                        "nominal": nominal,
                    }
                )
            )
    text = _report(args, space, motions, results, nominal, speed, meta)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
