"""The learnability ladder's measurement: does a checkpoint know what held-out designs do?

For a checkpoint and a held-out set (designs of its space that no training draw holds,
`tt.ladder.heldout_designs`, x validation motions, `tt.ladder.validation_motions`) it runs
`tt predict`'s code path (`tt.guidance.predicted.predict_designs`: the design given, as the
dynamics task's condition or inpainted into the robot task, the dynamics predicted, the
reward of those) and the simulator on the same pairs, and reports
the Pearson r pooled over all pairs and within each motion, beside the ceiling of the 8-step
reward estimate (the same estimator on the simulated poses). Targets (issue 17): R1
(``viperx-nominal``) pooled >= 0.8, within-motion >= 0.6; R2 (``viperx``) 0.7 and 0.5.

Prints one JSON line per result; writes a markdown report (``--out``, default
``runs/benchmarks/dit_ladder_<space>.md``, outside the results folder) and the raw numbers
beside it (``.json``).

Usage: ``python benchmarks/dit_ladder.py RUN_OR_CHECKPOINT [--designs 32] [--motions 5] [--samples 1]
[--num-steps 20] [--threads 2] [--via dynamics|inpaint] [--out runs/ladder/r2j/step_2000.md]``;
``python benchmarks/dit_ladder.py --summary DIR [--note TEXT] [--out FILE]`` tabulates the
``.json`` results in DIR (one per checkpoint or setting) into FILE (default DIR.md), e.g.
``--summary runs/ladder/r2j --out benchmarks/results/dit_ladder_r2j.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

#: Per-checkpoint reports and their raw numbers: run logs, outside the results folder.
RUNS = Path(__file__).resolve().parents[1] / "runs" / "benchmarks"


#: A simulated tracking reward below this is a design that (nearly) fails at once: less
#: than one perfectly tracked step's worth. On the full ViperX space about half the held-out
#: pairs do.
FAILED_BELOW = 1.0


def failure_split(predicted: np.ndarray, simulated: np.ndarray) -> dict:
    """How the predicted rewards separate pairs that fail in simulation (reward < FAILED_BELOW)
    from those that track: the failed share, the AUC (the chance that a tracking pair is
    predicted above a failing one; 0.5 is chance) and Pearson r among the tracking pairs."""
    from tt.ladder import pearson

    p, q = np.asarray(predicted, float).ravel(), np.asarray(simulated, float).ravel()
    failed = q < FAILED_BELOW
    out = {"failed_share": float(failed.mean()), "auc": float("nan")}
    if failed.any() and (~failed).any():
        a, b = p[~failed][:, None], p[failed][None, :]
        out["auc"] = float(np.mean((a > b) + 0.5 * (a == b)))
    out["r_tracking"] = pearson(p[~failed], q[~failed])
    return out


def summary(folder: Path, note: str, out: Path | None = None) -> Path:
    """`out` (default DIR.md): one row per result JSON in `folder`, by step then samples and DDIM steps."""
    results = [json.loads(p.read_text()) | {"file": p.name} for p in folder.glob("*.json")]
    results.sort(
        key=lambda r: (
            r.get("pairs", "held-out") != "held-out",
            r["step"],
            r.get("reward", "tracking"),
            r["samples"],
            r["num_steps"],
        )
    )
    lines = [
        f"# Ladder over a run: {folder.name}",
        "",
        note,
        "",
        f"Failing pairs: simulated reward below {FAILED_BELOW:g} (less than one perfectly tracked step). AUC: the "
        "chance that the model predicts a tracking pair above a failing one (0.5: chance). r tracking: Pearson r "
        "among the pairs that do not fail. Error at the query steps: the median over failing and over tracking pairs "
        "of the mean end-effector position error at the 8 query steps, counted or not, predicted / simulated [cm] "
        "(results written since 2026-12-03 evening).",
        "",
        "| step | pairs | reward | samples | DDIM steps | pooled r | mean within-motion r | within-motion r per "
        "motion | effort term r, pooled / within | failing (%) "
        "| AUC failing | r tracking | error failing (cm) | error tracking (cm) | predict (s) | file |",
        "|---:|---|---|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in results:
        per = " / ".join(f"{v:.2f}" for v in r["within_r"])
        # The cut is the tracking reward's (rewards without a "reward" field were tracking).
        tracking = r.get("reward", "tracking") == "tracking"
        f = (
            failure_split(r["predicted"], r["simulated"])
            if tracking and "predicted" in r and "simulated" in r
            else None
        )
        split = f"{100 * f['failed_share']:.0f} | {f['auc']:.2f} | {f['r_tracking']:.2f}" if f else "- | - | -"
        errors = "- | -"
        if f and "predicted_error_cm" in r:
            failed = np.asarray(r["simulated"], float) < FAILED_BELOW
            pe, se = np.asarray(r["predicted_error_cm"], float), np.asarray(r["simulated_error_cm"], float)
            errors = " | ".join(
                f"{np.median(pe[m]):.0f} / {np.median(se[m]):.0f}" if m.any() else "-" for m in (failed, ~failed)
            )
        term = f"{r['term']}: {r['term_pooled_r']:.2f} / {np.nanmean(r['term_within_r']):.2f}" if r.get("term") else "-"
        if r.get("estimator_term_within_r"):
            term += f" (8-step estimate on the simulated episode: {np.nanmean(r['estimator_term_within_r']):.2f})"
        lines.append(
            f"| {r['step']} | {r.get('pairs', 'held-out')} | {r.get('reward', 'tracking')} | {r['samples']} | "
            f"{r['num_steps']} | {r['pooled_r']:.2f} | {r['within_r_mean']:.2f} | "
            f"{per} | {term} | {split} | {errors} | {r['seconds']['predict']:.0f} | `{r['file']}` |"
        )
    out = Path(out) if out is not None else folder.with_suffix(".md")
    out.write_text("\n".join(lines + [""]))
    return out


def main() -> None:
    if "--summary" in sys.argv:
        p = argparse.ArgumentParser(description="tabulate ladder results")
        p.add_argument("--summary", required=True, type=Path)
        p.add_argument("--note", default="")
        p.add_argument("--out", type=Path, default=None, help="the table (default: DIR.md)")
        a = p.parse_args()
        print(f"wrote {summary(a.summary, a.note, a.out)}", file=sys.stderr)
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="checkpoint file or run folder")
    p.add_argument("--space", default=None, help="design space (default: the checkpoint's)")
    p.add_argument("--designs", type=int, default=32, help="held-out designs")
    p.add_argument("--design-seed", type=int, default=0)
    p.add_argument("--motions", type=int, default=5, help="validation motions (spread over the skills)")
    p.add_argument("--reward", default="tracking")
    p.add_argument("--samples", type=int, default=1, help="samples averaged per design x motion")
    p.add_argument("--num-steps", type=int, default=20, help="DDIM steps of the prediction")
    p.add_argument("--chunk", type=int, default=None, help="sequences per sampling call")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--backend", default=None, help="simulator of the rewards (default: the space's, mjbatch for contacts)"
    )
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--via",
        default=None,
        choices=["dynamics", "inpaint"],
        help="how the design is given (default: dynamics when the checkpoint was trained on it)",
    )
    p.add_argument(
        "--online-refresh",
        type=int,
        default=None,
        metavar="K",
        help="score the designs x training motions of refresh K of the checkpoint's own online run (its "
        "training data: in its buffer, long past, or not yet drawn) instead of held-out designs",
    )
    p.add_argument("--out", default=None)
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    from tt.dit.checkpoint import load_model
    from tt.guidance.predicted import default_via
    from tt.ladder import heldout_designs, score_designs, validation_motions

    trained = load_model(args.checkpoint, device=args.device)
    space = args.space or trained.space
    if space is None:
        p.error("the checkpoint records no design space; give --space")
    if args.backend is None:
        from tt.sim.backends import default_backend

        args.backend = default_backend(space)
    if args.online_refresh is None:
        designs = heldout_designs(space, args.designs, args.design_seed)
        motions = validation_motions(space, args.motions)
        pairs = "held-out"
    else:
        from tt.dit.checkpoint import load_checkpoint
        from tt.dit.online import OnlineConfig, OnlineTokenSource

        online = (load_checkpoint(trained.path).get("train_config") or {}).get("online")
        if not online:
            p.error(
                f"--online-refresh: {trained.path} records no online run (a resumable checkpoint of `tt train "
                "--online`)"
            )
        designs, motions = OnlineTokenSource(OnlineConfig(**online), device="cpu").draw(args.online_refresh)
        designs = designs[: args.designs]
        pairs = f"online refresh {args.online_refresh}"
    sc = score_designs(
        trained,
        designs,
        motions,
        args.reward,
        samples=args.samples,
        num_steps=args.num_steps,
        chunk=args.chunk,
        backend=args.backend,
        device=args.device,
        via=args.via,
    )
    via = args.via or default_via(trained)
    result = {
        "bench": "dit_ladder",
        "checkpoint": str(trained.path),
        "step": trained.step,
        "space": space,
        "designs": len(designs),
        "pairs": pairs,
        "reward": args.reward,
        "motions": sc.motions,
        "via": via,
        "samples": args.samples,
        "num_steps": args.num_steps,
        "pooled_r": sc.pooled,
        "within_r_mean": sc.within_mean,
        "within_r": sc.within,
        "estimator_pooled_r": sc.estimator_pooled,
        "seconds": sc.seconds,
    }
    if sc.term is not None:
        result |= {
            "term": sc.term,
            "term_pooled_r": sc.term_pooled,
            "term_within_r": sc.term_within,
            "estimator_term_within_r": sc.estimator_term_within,
        }
    print(json.dumps(result), flush=True)
    suffix = "" if args.online_refresh is None else f"_online{args.online_refresh}"
    out = Path(args.out) if args.out else RUNS / f"dit_ladder_{space}{suffix}.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = [
        f"| {m} | {sc.predicted[:, j].mean():.1f} | {sc.simulated[:, j].mean():.1f} | {sc.within[j]:.2f} | "
        f"{sc.estimator_within[j]:.2f} |"
        for j, m in enumerate(sc.motions)
    ]
    out.write_text(
        "\n".join(
            [
                f"# Ladder: predicted vs simulated {args.reward} reward, {space}",
                "",
                machine_header(args.device),
                f"Checkpoint `{trained.path}` (step {trained.step}); "
                + (
                    f"{len(designs)} held-out designs (`tt.ladder.heldout_designs({space!r}, {args.designs}, "
                    f"{args.design_seed})`) "
                    f"x {len(motions)} validation motions"
                    if args.online_refresh is None
                    else f"the first {len(designs)} designs x {len(motions)} training motions of its run's online "
                    "refresh "
                    f"{args.online_refresh} (training data)"
                )
                + f"; `tt predict` code path (design given via {via}), {args.samples} sample(s), "
                f"{args.num_steps} DDIM steps; simulator "
                f"`{args.backend}`.",
                "",
                f"- pooled Pearson r: **{sc.pooled:.2f}** (estimator on the simulated poses: "
                f"{sc.estimator_pooled:.2f})",
                f"- mean within-motion r: **{sc.within_mean:.2f}**",
                *(
                    []
                    if sc.term is None
                    else [
                        f"- the reward's {sc.term} term (mean actuator {sc.term} norm), predicted against simulated: "
                        f"pooled r **{sc.term_pooled:.2f}**, mean within-motion r "
                        f"**{np.nanmean(sc.term_within):.2f}** (the 8-step estimate on the simulated episode: "
                        f"{np.nanmean(sc.estimator_term_within):.2f} within-motion)"
                    ]
                ),
                "",
                "| motion | predicted mean | simulated mean | within-motion r | estimator r |",
                "|---|---:|---:|---:|---:|",
                *rows,
                "",
                f"Time: predict {sc.seconds['predict']:.0f} s, simulate {sc.seconds['simulate']:.0f} s.",
                "",
            ]
        )
    )
    out.with_suffix(".json").write_text(json.dumps({**result, **sc.to_dict()}, indent=1))
    print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
