"""Which training choices let the DiT learn what a design does: R0-sized ablations.

Every row trains the same `tiny` model for the same steps on R0's data (the 64 episodes of
one online refresh of ``viperx-nominal``: 16 designs x 4 augmented training motions, no
control perturbation, terminated episodes kept to the motion's end; `tests/test_ladder.py`)
and scores each checkpoint as R0 does: `tt predict`'s code path on those designs x motions
(20 DDIM steps, one sample) against the simulator, pooled and within-motion Pearson r. The
rows change one choice at a time, from the paper's recipe (robot task with the design
inpainted, eps prediction, a learned time-ID table) to tt's (the dynamics task, sinusoidal
time IDs, x0 prediction with the track-link pose anchored on its target).

Each row runs on one thread and writes ``runs/benchmarks/dit_recipe/damped_start/<row>.json``
(a run log, outside the results folder), so two processes can share a 2-core machine
(``--rows a b`` and ``--rows c d``); ``--report`` renders every row written so far into
``benchmarks/results/dit_recipe.md``. Rows in ``runs/benchmarks/dit_recipe/*.json`` (the
committed report's older rows, in git before issue 52) were trained and scored before the start
posture had its own IK damping (2026-12-03, `tt.sim.controller.IKConfig.init_damping`), when
the reward was close to noise in the design; the report keeps them in a table of their own.

Usage: ``python benchmarks/dit_recipe.py [--rows NAME ...] [--steps 1000] [--report]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

RESULTS = Path(__file__).parent / "results"
#: The rows' raw results: run logs, outside the results folder (runs/ is not tracked).
ROWS_DIR = Path(__file__).resolve().parents[1] / "runs" / "benchmarks" / "dit_recipe"
#: Rows on today's data (the damped start posture); ROWS_DIR itself holds the older rows.
CURRENT_DIR = ROWS_DIR / "damped_start"

_ANCHOR = dict(task="dynamics", prediction="x0", anchor_track=True)

#: name -> (what changes, TrainConfig fields over `tt.ladder.R0_TRAINING`, how `tt predict`
#: gives the design).
RECIPES: dict[str, tuple[str, dict, str]] = {
    "paper": (
        "the paper's: robot task, design inpainted, eps, learned time IDs",
        dict(task="robot", prediction="eps", time_ids="learned"),
        "inpaint",
    ),
    "dynamics": (
        "+ dynamics task (design a clean condition)",
        dict(task="dynamics", prediction="eps", time_ids="learned"),
        "dynamics",
    ),
    "sinusoidal": ("+ sinusoidal time IDs", dict(task="dynamics", prediction="eps"), "dynamics"),
    "x0": ("+ x0 prediction (R0's recipe, `tests/test_ladder.py`)", dict(task="dynamics", prediction="x0"), "dynamics"),
    "anchor": (
        "x0, and the track-link pose anchored on its target",
        dict(task="dynamics", prediction="x0", anchor_track=True),
        "dynamics",
    ),
    "robot_x0": (
        "the robot task with the design inpainted, with sinusoidal time IDs and x0 prediction",
        dict(task="robot", prediction="x0"),
        "inpaint",
    ),
    "robot+dynamics": (
        "robot and dynamics tasks, half the batch each, x0 + anchor (a generator that is also a critic)",
        dict(task="robot+dynamics", prediction="x0", anchor_track=True),
        "dynamics",
    ),
    # One change each from `anchor` (v: from `x0`, as the anchor needs x0 prediction).
    "v": ("v prediction (compare with `x0`: the anchor needs x0)", dict(task="dynamics", prediction="v"), "dynamics"),
    "min_snr": ("`anchor` + min-SNR-5 loss weighting", dict(_ANCHOR, weighting="min_snr"), "dynamics"),
    "edm": ("`anchor` + EDM loss weighting", dict(_ANCHOR, weighting="edm"), "dynamics"),
    "lr_low": ("`anchor` at half the learning rate (2.5e-3)", dict(_ANCHOR, lr=2.5e-3), "dynamics"),
    "lr_high": ("`anchor` at twice the learning rate (1e-2)", dict(_ANCHOR, lr=1e-2), "dynamics"),
    "batch64": ("`anchor` with batch 64 (twice the windows per step)", dict(_ANCHOR, batch_size=64), "dynamics"),
    "mini": ("`anchor` with the `mini` model (128 wide, 4 blocks)", dict(_ANCHOR, size="mini"), "dynamics"),
    "T50": ("`anchor` with 50 DDIM training steps (of 100)", dict(_ANCHOR, robot_diffusion_steps=50), "dynamics"),
    "bf16": ("`anchor` with bf16 autocast on the CPU", dict(_ANCHOR, bf16_cpu=True), "dynamics"),
}


#: What the rows decided (kept beside the table, which `report` rewrites).
KEPT = (
    "Kept: x0 prediction and sinusoidal time-step IDs are now `tt train`'s defaults. The dynamics task is what "
    "`tt predict` needs from a checkpoint (`--task dynamics`, or `robot+dynamics` for a model that also "
    "generates): with x0 it is the difference between 0.30 (robot task, design inpainted) and 0.97. The anchor "
    "(`--anchor-track`) stays an option: it learns a little faster early (0.40 against 0.26 at step 250) and ends "
    "level. Sharing the batch with the robot task halves the critic's windows and costs most of the gain at this "
    "budget. Not measured here: noise-level weightings, learning rate and batch, model sizes, DDIM training "
    "steps, bf16 on the CPU, and data choices (issue 17 lists them)."
)


#: What today's rows decided (written once they are measured).
CURRENT_NOTE = (
    "On today's data R0 is harder (more designs survive, their rewards lie closer), so the rows "
    "separate more. `anchor`, the shipped recipe, reaches 0.98 at 1,000 steps; EDM weighting learns a "
    "little slower early (0.27 against 0.36 at step 250) and ends level (0.97); min-SNR-5 is clearly worse "
    "(0.81 at 1,000). Half the learning rate (2.5e-3) starts slower (0.10 at 250) and ends at 0.93; twice "
    "(1e-2) ends lower (0.94). v prediction ends at 0.82 (the anchor needs x0, so it is one change from "
    "plain x0). 50 DDIM training steps instead of 100: 0.88. Batch 64 is ahead per step (0.87 at 500, 0.99 "
    "at 1,000) but runs at half the steps per second: at the same windows seen it is behind (0.87 at its "
    "step 500 against `anchor`'s 0.98 at 1,000). The `mini` model reaches 0.99 at 1,000 steps (0.98 at "
    "750) at a fifth of `tiny`'s steps per second (0.93 against 4.5 on one core), so at equal time `tiny` "
    "is ahead on R0; R1 and R2, with thousands of designs rather than 16, use `mini`. Kept: no loss "
    "weighting, x0 prediction, R0's learning rate, batch 32 and 100 DDIM steps, as `tt train` does now. "
    "bf16 autocast on this CPU (AVX-512 BF16 and AMX): 0.97 at 1,000 steps (0.37 / 0.66 / 0.93 at 250 to "
    "750 against 0.36 / 0.72 / 0.94) at 3.2 steps/s against `anchor`'s 4.4, the two run side by side (`anchor` "
    "rerun with it: the same r curve, 4.36 steps/s): slower and no better on this model size, so fp32 "
    "stays on the CPU."
)


def run_row(name: str, steps: int, out: Path) -> dict:
    from tt.dit.checkpoint import list_checkpoints, load_model
    from tt.dit.online import OnlineTokenSource
    from tt.dit.train import TrainConfig, train
    from tt.ladder import R0_TRAINING, r0_online, score_designs
    from tt.sim.controller import IKConfig

    what, fields, via = RECIPES[name]
    online = r0_online()
    shared = {**R0_TRAINING, **fields}
    config = TrainConfig(
        out=str(out / name),
        device="cpu",
        steps=steps,
        checkpoint_every=max(1, steps // 4),
        keep_checkpoints=4,
        online=online,
        resume=False,
        **shared,
    )
    t0 = time.perf_counter()
    result = train(config)
    seconds = time.perf_counter() - t0
    designs, motions = OnlineTokenSource(online, device="cpu").draw(0)
    curve = []
    for path in list_checkpoints(out / name):
        trained = load_model(path)
        sc = score_designs(trained, designs, motions, num_steps=20, via=via)
        curve.append(
            {
                "step": trained.step,
                "pooled_r": sc.pooled,
                "within_r": sc.within,
                "within_r_mean": sc.within_mean,
                "estimator_pooled_r": sc.estimator_pooled,
            }
        )
    losses = result.losses.numpy()
    return {
        "row": name,
        "what": what,
        "fields": fields,
        "via": via,
        "steps": steps,
        "batch_size": shared["batch_size"],
        "samples_seen": steps * shared["batch_size"],
        "init_damping": IKConfig().init_damping,
        "measured": machine_header("cpu").strip().splitlines()[:2],
        "train_seconds": seconds,
        "steps_per_s": steps / seconds,
        "parameters": result.parameters,
        "final_loss_mean_last_50": float(losses[-50:].mean()),
        "curve": curve,
        "command": f"python benchmarks/dit_recipe.py --rows {name} --steps {steps}",
    }


def _table(rows: list[dict]) -> list[str]:
    order = list(RECIPES)
    rows = sorted(rows, key=lambda r: order.index(r["row"]) if r["row"] in order else len(order))
    lines = [
        "| row | change | design given | pooled r (per checkpoint) | within-motion r (last) | steps/s | windows seen |",
        "|---|---|---|---|---|---:|---:|",
    ]
    for r in rows:
        curve = ", ".join(f"{c['pooled_r']:.2f}@{c['step']}" for c in r["curve"])
        within = " / ".join(f"{v:.2f}" for v in r["curve"][-1]["within_r"]) if r["curve"] else "-"
        lines.append(
            f"| `{r['row']}` | {r['what']} | {r['via']} | {curve} | {within} | {r['steps_per_s']:.2f} | "
            f"{r['samples_seen']:,} |"
        )
    return lines


def report() -> Path:
    from tt.ladder import R0_TRAINING

    current = [json.loads(p.read_text()) for p in sorted(CURRENT_DIR.glob("*.json"))]
    older = [json.loads(p.read_text()) for p in sorted(ROWS_DIR.glob("*.json"))]
    if not current and not older:
        raise SystemExit(f"no rows in {ROWS_DIR}: run some with --rows first")
    lines = [
        "# DiT recipe: what lets the model learn what a design does (R0-sized ablations)",
        "",
        machine_header("cpu"),
        "(the date above is this report's; each section says when its rows were measured)",
        "",
        "Each row: a `tiny` model trained on R0's 64 episodes (16 `viperx-nominal` designs x 4 "
        "augmented training motions, `tests/test_ladder.py`), one thread, then `tt predict`'s code "
        "path on those same pairs (20 DDIM steps, one sample) against the simulator. Shared unless the row "
        f"changes it: {json.dumps(R0_TRAINING)} (`tt.ladder.R0_TRAINING`). R0's target: pooled r >= 0.95. Rows "
        "were run two at a time on the 2-core machine (one thread each), so steps/s is per core under that load.",
        "",
    ]
    if current:
        dates = sorted(r["measured"][0].removeprefix("- date: ") for r in current if r.get("measured"))
        machines = sorted({r["measured"][1].removeprefix("- machine: ") for r in current if r.get("measured")})
        lines += [
            "## Today's data (start posture with its own IK damping, 2026-12-03)",
            "",
            f"Rows finished {dates[0]} to {dates[-1]} on {'; '.join(machines)}." if dates else "",
            "",
            CURRENT_NOTE,
            "",
            *_table(current),
            "",
            "Commands: " + "; ".join(f"`{r['command']}`" for r in current),
            "",
        ]
    lines += (
        []
        if not older
        else [
            "## Before the damped start posture (2026-12-02)",
            "",
            "Measured 2026-12-02 01:05 UTC on the 2-core AMD EPYC. "
            "The reward was then close to noise in the design (`reward_reliability_*.md`); R0's designs "
            "failed more often, so their rewards lay further apart and 1,000 steps were enough.",
            "",
            *_table(older),
            "",
            KEPT,
            "",
            "Commands: " + "; ".join(f"`{r['command']}`" for r in older),
            "",
        ]
    )
    out = RESULTS / "dit_recipe.md"
    out.write_text("\n".join(lines))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", nargs="*", default=[], choices=list(RECIPES), help="rows to run (default: none)")
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--runs", default="runs/dit_recipe", help="folder of the rows' training runs")
    p.add_argument(
        "--report", action="store_true", help="render benchmarks/results/dit_recipe.md from every row written"
    )
    args = p.parse_args()
    torch.set_num_threads(1)
    CURRENT_DIR.mkdir(parents=True, exist_ok=True)
    for name in args.rows:
        row = run_row(name, args.steps, Path(args.runs))
        (CURRENT_DIR / f"{name}.json").write_text(json.dumps(row, indent=1))
        last = row["curve"][-1] if row["curve"] else {}
        print(
            json.dumps(
                {
                    "row": name,
                    "pooled_r": last.get("pooled_r"),
                    "within_r": last.get("within_r"),
                    "steps_per_s": row["steps_per_s"],
                }
            ),
            flush=True,
        )
    if args.report or not args.rows:
        print(f"wrote {report()}", file=sys.stderr)


if __name__ == "__main__":
    main()
