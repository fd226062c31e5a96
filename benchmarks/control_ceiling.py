"""A supervised ceiling for the control task (issue 17): what the control windows allow.

The DiT controller (`tt.dit.policies.ModelPolicy`) is given a window's clean conditions (the
embodiment tokens, the current state, the last command and the targets of 8 consecutive
steps) and asked for DiffIK's next command (window slot 1). Trained that way, every checkpoint
so far lands at "repeat the last command" (`dit_control.md`). This fits a plain MLP on
exactly those conditions, normalised as the DiT sees them, to the next command's offset from
the last one, for several training-set sizes, and measures it as the DiT is measured:

* one step (teacher-forced) on fresh episodes of held-out designs, the RMSE of the next
  command against DiffIK's beside holding the current joints and repeating the last command
  (`dit_eval.teacher_forced`'s windows: seed `--design-seed`, no control perturbation);
* in closed loop (`tt.dit.closed_loop`, Warp physics): the MLP chooses every command on
  held-out designs x validation motions, scored as a share of the MuJoCo + mink oracle's
  tracking reward on the same pairs, beside DiffIK itself in the same loop (the teacher).

It separates what the data allows at a given number of windows from what the diffusion
training reaches: a regressor that cannot control from 100k windows says the DiT will not
either at that budget.

Levers (``--variants``, one row per variant and training size; ``ANCHOR/LOSS[/film][/daggerK]``):

* anchor ``command``: the offset from the last command, which the regressor is given (the
  DiT's ``--anchor-control command --known-command``); ``joints``: DiffIK's own form, the next
  command's offset from the current joint positions, the last command left out of the features;
* loss ``mse``, or ``huber`` (`--huber-delta` in units of the offset's RMS): DiffIK's
  increments are heavy-tailed (the header gives the share of their squares the largest 1 % of
  windows carry), and a squared loss fits those few;
* ``daggerK``: K rounds of DAgger. Each runs the regressor in closed loop on
  `--dagger-refreshes` online refreshes of new training designs and motions, labels every
  state it visits with DiffIK's command from that state (`tt.dit.policies.IKPolicy`), adds
  those windows to the training set and refits; a row per round. A window's last command is
  the one the regressor executed, its next command DiffIK's label;
* model ``film`` (``ANCHOR/LOSS/film``): the design modulates every hidden layer of an MLP of
  the state and targets (`FiLMRegressor`) instead of entering the plain MLP beside them.

``--trim Q`` fits without the windows whose offset exceeds, in any joint, that joint's Q
quantile, so that the small steady increments carry the fit; ``--loop-designs seen`` runs the
closed loop on designs the regressor trained on instead of held-out ones; ``--pool N`` makes
every window one of N designs' (on fresh motions); with N = 1 it is the control task's
memorisation rung.

Every row also reports how far the regressor moves the command from its anchor on the states
it visits itself, relative to DiffIK's move from the same states (1: as far as DiffIK); and
``--ik-noise`` adds DiffIK with Gaussian command noise in the same loop, which tells errors a
closed loop tolerates from errors it does not.

Usage: ``python benchmarks/control_ceiling.py [--rows 16384x20 65536x20 262144x20 98304x1]
[--variants command/mse,joints/huber/dagger2] [--ik-noise 0.03]`` (training windows x epochs per
row; the last row sees about the DiT's 96,000 windows); writes
``benchmarks/results/control_ceiling.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from dit_eval import RESULTS, SPACE, cut, pearson, validation_motions  # noqa: E402
from machine import machine_header, write_report  # noqa: E402

from tt.dit.control_ceiling import (  # noqa: E402
    STEPS,
    DesignPool,
    NoisyIK,
    Variant,
    Windows,
    dagger_windows,
    draw_windows,
    fit,
    one_step,
    regressor_policy,
    tail_share,
    trimmed,
)


def emit(**fields) -> dict:
    print(json.dumps({"bench": "control_ceiling", **fields}), flush=True)
    return fields


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--rows",
        nargs="+",
        default=["16384x20", "65536x20", "262144x20", "98304x1"],
        help="one row per WINDOWSxEPOCHS: the first WINDOWS training windows, EPOCHS passes over them",
    )
    parser.add_argument(
        "--variants",
        default="command/mse",
        help="comma-separated ANCHOR/LOSS[/film][/daggerK] (anchor: command, joints; loss: mse, huber; "
        "film: the design modulates every hidden layer); "
        "every variant runs every row",
    )
    parser.add_argument("--huber-delta", type=float, default=0.1, help="huber loss: delta in units of the offset's RMS")
    parser.add_argument(
        "--trim",
        type=float,
        default=1.0,
        help="fit without the training windows whose offset exceeds, in any joint, that joint's TRIM "
        "quantile (e.g. 0.9; 1: keep all): the rare large jumps that dominate a squared loss",
    )
    parser.add_argument(
        "--dagger-refreshes", type=int, default=2, help="DAgger: online refreshes of new designs per round"
    )
    parser.add_argument("--dagger-windows", type=int, default=32768, help="DAgger: windows added per round")
    parser.add_argument(
        "--ik-noise", default="", help="comma-separated stds [rad]: DiffIK with command noise in the same loop"
    )
    parser.add_argument(
        "--refreshes",
        type=int,
        default=16,
        help="online refreshes (64 new designs x 4 motions each) the training windows are drawn from: the designs seen",
    )
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--hidden", type=int, default=512, help="width of the regressor's hidden layers")
    parser.add_argument("--depth", type=int, default=3, help="hidden layers of the regressor")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0, help="training data and MLP seed")
    parser.add_argument("--design-seed", type=int, default=20261122, help="held-out designs and one-step windows")
    parser.add_argument("--designs", type=int, default=25, help="designs of the closed loop")
    parser.add_argument(
        "--pool",
        type=int,
        default=None,
        metavar="N",
        help="train, test and run the closed loop on a pool of N designs (`space.sample(N, seed="
        "--pool-seed)`; the loop on the first --designs of them), on fresh motions each time: "
        "whether the windows carry what control needs when the designs are few and known",
    )
    parser.add_argument("--pool-seed", type=int, default=3, help="--pool: seed of the pool's designs")
    parser.add_argument(
        "--loop-designs",
        choices=("held-out", "seen"),
        default="held-out",
        help="closed loop on held-out designs, or on designs of the last training refresh (what a "
        "regressor that learned those designs, not kinematics, can do)",
    )
    parser.add_argument("--motions", type=int, default=5, help="validation motions of the closed loop")
    parser.add_argument("--test-windows", type=int, default=4096, help="one-step windows of held-out designs")
    parser.add_argument(
        "--space",
        choices=("viperx", "viperx-nominal"),
        default=SPACE,
        help="design space of every design: the full ViperX space, or one structure (the nominal "
        "discrete choices, continuous ones varied: the ladder's R1)",
    )
    parser.add_argument("--out", default=str(RESULTS / "control_ceiling.md"))
    args = parser.parse_args()
    try:
        plan = [(int(w), float(e)) for w, _, e in (r.partition("x") for r in args.rows)]
    except ValueError:
        parser.error(f"--rows {args.rows}: each row is WINDOWSxEPOCHS, e.g. 65536x20")
    if any(w < 1 or not e > 0 for w, e in plan):
        parser.error(f"--rows {args.rows}: windows must be >= 1 and epochs > 0")
    try:
        variants = [Variant.parse(v) for v in args.variants.split(",") if v.strip()]
        noise = [float(x) for x in args.ik_noise.split(",") if x.strip()]
    except ValueError as e:
        parser.error(str(e))
    if not variants:
        parser.error("--variants is empty")
    if any(not (x >= 0) for x in noise):
        parser.error(f"--ik-noise {args.ik_noise}: stds must be >= 0")
    if args.pool is not None and (args.loop_designs != "held-out" or args.pool < 1):
        parser.error("--pool N (N >= 1) runs the closed loop on the pool's designs; leave --loop-designs out")
    if not 0.5 <= args.trim <= 1.0:
        parser.error(f"--trim {args.trim}: a quantile in [0.5, 1]")
    if args.hidden < 1 or args.depth < 1:
        parser.error(f"--hidden {args.hidden} --depth {args.depth}: both must be >= 1")
    if not args.huber_delta > 0 or args.dagger_refreshes < 1 or args.dagger_windows < 1:
        parser.error("--huber-delta must be > 0, --dagger-refreshes and --dagger-windows >= 1")
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from tt.baselines.evaluate import score_episode
    from tt.dit.closed_loop import closed_loop_rollout
    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.dit.policies import HoldPolicy, IKPolicy
    from tt.sim.designs import get_space
    from tt.sim.validate import oracle_rollout

    load_before, started = os.getloadavg(), time.perf_counter()
    # The DiT's training data: tt generate's draws, control perturbation included.
    cfg = OnlineConfig(space=args.space, seed=args.seed, refresh_every=1, buffer=1)
    if args.loop_designs == "seen" and args.designs > cfg.designs:
        parser.error(f"--designs {args.designs}: a refresh has {cfg.designs} designs to take seen ones from")
    train_src = OnlineTokenSource(cfg, device="cpu")
    space = get_space(args.space)
    pool = None
    if args.pool is not None:
        pool = space.sample(args.pool, seed=args.pool_seed)
        train_src.space = DesignPool(train_src.space, pool)
    layout, norm = train_src.layout(STEPS), train_src.fit_normalizer()
    test_src = OnlineTokenSource(OnlineConfig(space=args.space, seed=args.design_seed, action_noise=0.0), device="cpu")
    if pool is not None:
        test_src.space = DesignPool(test_src.space, pool)
    test = draw_windows(test_src, args.test_windows, layout, norm, args.seed + 1)
    y_test = test.c1 - test.c0
    tails = {
        "top1": tail_share(y_test, test.real, 0.01),
        "top5": tail_share(y_test, test.real, 0.05),
        "median": float(y_test[test.real].abs().median()),
        "rms": float(y_test[test.real].pow(2).mean().sqrt()),
    }
    emit(**{f"tail_{k}": v for k, v in tails.items()})

    if pool is not None:
        designs = pool[: args.designs]
    elif args.loop_designs == "seen":
        designs = train_src.draw(args.refreshes - 1)[0][: args.designs]
    else:
        designs = space.sample(args.designs, seed=args.design_seed)
    motions = cut(validation_motions(args.motions), 0)
    t = time.perf_counter()
    r_oracle, m_oracle = score_episode(oracle_rollout(designs, motions), designs, motions, "tracking")
    emit(oracle_reward=float(r_oracle.mean()), seconds=time.perf_counter() - t)
    r_ik, m_ik = score_episode(closed_loop_rollout(designs, motions, IKPolicy()), designs, motions, "tracking")
    emit(ik_share=float(r_ik.mean() / r_oracle.mean()))
    r_still, m_still = score_episode(closed_loop_rollout(designs, motions, HoldPolicy()), designs, motions, "tracking")
    emit(repeat_share=float(r_still.mean() / r_oracle.mean()))
    noisy = []
    for sigma in noise:
        r, m = score_episode(
            closed_loop_rollout(designs, motions, NoisyIK(sigma, args.seed)), designs, motions, "tracking"
        )
        noisy.append(
            emit(ik_noise=sigma, share=float(r.mean() / r_oracle.mean()), survival=float(np.mean(m["survival"])))
        )

    t = time.perf_counter()
    train = draw_windows(train_src, max(w for w, _ in plan), layout, norm, args.seed, refreshes=args.refreshes)
    # Other windows of the training designs (another draw of the last refresh's episodes):
    # generalising to new windows of designs seen, against generalising to new designs.
    seen = draw_windows(train_src, args.test_windows, layout, norm, args.seed + 2)
    gen_s = time.perf_counter() - t
    emit(episodes=train_src.stats["episodes"], generate_seconds=gen_s)

    def measure(data: Windows, variant: Variant, epochs: float, **extra) -> tuple[dict, torch.nn.Module]:
        t = time.perf_counter()
        windows = len(data)
        data = trimmed(data, variant, args.trim)
        model, losses = fit(
            data,
            variant,
            epochs=epochs,
            batch=args.batch,
            lr=args.lr,
            seed=args.seed,
            huber_delta=args.huber_delta,
            layout=layout,
            hidden=args.hidden,
            depth=args.depth,
        )
        fit_s = time.perf_counter() - t
        step = one_step(model, test, variant)
        step["r2_seen"] = one_step(model, seen, variant)["r2"]
        t = time.perf_counter()
        policy = regressor_policy(model, layout, norm, variant, space=args.space)
        ep = closed_loop_rollout(designs, motions, policy)
        loop_s = time.perf_counter() - t
        r, m = score_episode(ep, designs, motions, "tracking")
        row = emit(
            variant=variant.label,
            windows=windows,
            fitted=len(data),
            epochs=epochs,
            samples=len(losses) * args.batch,
            fit_seconds=fit_s,
            loss=float(np.mean(losses[-50:])),
            **step,
            share=float(r.mean() / r_oracle.mean()),
            pos_err_cm=float(np.nanmean(m["pos_err"])),
            survival=float(np.mean(m["survival"])),
            pearson=pearson(r_oracle.ravel(), r.ravel()),
            moved=policy.moved / max(policy.ik_moved, 1e-12),
            loop_seconds=loop_s,
            **extra,
        )
        return row, model

    rows = []
    for variant in variants:
        for n, epochs in plan:
            data = train.take(slice(0, n))
            row, model = measure(data, variant, epochs)
            rows.append(row)
            for rnd in range(1, variant.dagger + 1):
                added = []
                for j in range(args.dagger_refreshes):
                    k = args.refreshes + (rnd - 1) * args.dagger_refreshes + j  # designs no earlier draw saw
                    share = args.dagger_windows // args.dagger_refreshes + (
                        j < args.dagger_windows % args.dagger_refreshes
                    )
                    w, stats = dagger_windows(train_src, k, model, layout, norm, variant, share, args.seed + 1000 + k)
                    emit(dagger_round=rnd, refresh=k, **stats)
                    added.append(w)
                data = Windows.cat([data, *added])
                row, model = measure(data, variant, epochs, dagger_round=rnd)
                rows.append(row)
    load_after = os.getloadavg()
    ik_noise = "; ".join(
        f"DiffIK with command noise of std {r['ik_noise']:g} rad: {100 * r['share']:.1f} %, survival "
        f"{100 * r['survival']:.0f} %"
        for r in noisy
    )
    lines = [
        f"# A supervised ceiling for the control task ({args.space})",
        "",
        machine_header("cpu").rstrip(),
        f"- torch threads {torch.get_num_threads()}; load average (1 min) before / after: {load_before[0]:.1f} / "
        f"{load_after[0]:.1f}; {time.perf_counter() - started:.0f} s in all",
        f"- command: `python benchmarks/control_ceiling.py {' '.join(sys.argv[1:])}`",
        f"- training windows: 8 consecutive steps of {train_src.stats['episodes']} episodes of "
        + (f"a pool of {args.pool} designs " if pool is not None else f"{args.refreshes * cfg.designs} designs ")
        + f"({args.refreshes} online refreshes of {cfg.designs} {'draws from it' if pool is not None else 'designs'} x "
        f"{cfg.motions} motions, seed {args.seed}, control perturbation {cfg.action_noise}; {gen_s:.0f} s to "
        "generate and "
        "draw), an equal share from each refresh in a random order, the first N of that draw per row; "
        "features: the DiT control query's clean "
        f"conditions ({train.X.shape[1]} values: embodiment, step 0's state and command, 8 target poses; the "
        "joints anchor "
        f"leaves the command out: {len(train.free)}), normalised as the DiT reads them; MLP {args.depth} x "
        f"{args.hidden} (GELU"
        + (
            "; film: the same over the columns other than the embodiment's, each hidden layer scaled and "
            f"shifted by an MLP {args.hidden} "
            "of the embodiment columns"
            if any(v.model == "film" for v in variants)
            else ""
        )
        + f"), batch "
        f"{args.batch}, AdamW lr {args.lr:g} one-cycle; target: the next command's offset from the variant's "
        "anchor (the last "
        "command, or the current joints), per joint in units of its RMS, squared (mse) or huber loss "
        f"(delta {args.huber_delta:g}) masked to real slots",
        f"- one step: {args.test_windows} windows of fresh episodes of "
        f"{'the same designs on other motions' if pool is not None else 'other designs'} (online refresh 0, seed "
        f"{args.design_seed}, no perturbation), as `dit_control.md`'s. DiffIK's increments (next command "
        "minus the last) are "
        f"heavy-tailed: median |increment| {tails['median']:.4f} rad, RMS {tails['rms']:.4f} rad; the largest "
        "1 % of them "
        f"carry {100 * tails['top1']:.0f} % of the summed squares (the largest 5 %: {100 * tails['top5']:.0f} "
        "%), so RMSE and "
        "R^2 over all windows mostly score those few; 'typical' R^2 leaves out each slot's largest 1 %",
        "- closed loop: "
        + (
            f"{len(designs)} of the {args.pool} designs every window is of (`space.sample({args.pool}, "
            f"seed={args.pool_seed})`; training and one-step windows are those designs on fresh training "
            "motions)"
            if pool is not None
            else f"{len(designs)} held-out {args.space} designs (`space.sample({args.designs}, "
            f"seed={args.design_seed})`)"
            if args.loop_designs == "held-out"
            else f"{len(designs)} designs the regressor trained on (the first of online refresh {args.refreshes - 1})"
        )
        + " x "
        f"{len(motions)} validation motions ({', '.join(m.name for m in motions)}), Warp physics; oracle "
        "(MuJoCo C + mink) "
        f"mean tracking reward {r_oracle.mean():.1f}, pos err {np.nanmean(m_oracle['pos_err']):.1f} cm, survival "
        f"{100 * np.mean(m_oracle['survival']):.0f} %; DiffIK in the same closed loop (the teacher): "
        f"{100 * r_ik.mean() / r_oracle.mean():.1f} % of the oracle, pos err {np.nanmean(m_ik['pos_err']):.1f} cm; "
        "repeating the start posture's command every step (a still arm): "
        f"{100 * r_still.mean() / r_oracle.mean():.1f} %, "
        f"pos err {np.nanmean(m_still['pos_err']):.1f} cm, survival {100 * np.mean(m_still['survival']):.0f} %"
        + (f"; {ik_noise}" if ik_noise else ""),
        *(
            [
                "- trimmed: each fit leaves out the windows whose offset from the anchor exceeds, in any "
                "joint, that joint's "
                f"{args.trim:g} quantile (the 'fitted' column counts the rest; epochs are passes over those)"
            ]
            if args.trim < 1
            else []
        ),
        "- moved: on the states the regressor visits in closed loop, the mean |offset from its anchor| of "
        "its commands over "
        "DiffIK's from the same states (1: it moves the command as far as DiffIK would)",
        f"- DAgger rounds (variants .../daggerK): {args.dagger_refreshes} online refreshes of new designs per round, "
        f"{args.dagger_windows:,} windows of the regressor's own closed-loop episodes labelled by DiffIK "
        "added per round, refit "
        "on everything so far",
        "- targets (issue 17, for the DiT): >= 50 % of the oracle's reward; one-step RMSE <= half of holding's",
        "",
        "| variant | DAgger round | training windows | fitted | epochs | samples seen | fit (s) | one-step "
        "RMSE (rad) | hold RMSE | repeat RMSE "
        "| R^2 of the increment, held-out designs | typical R^2 | R^2, training designs' other windows | "
        "moved | share of oracle reward "
        "| pos err (cm) | survival (%) | r vs oracle |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['variant']} | {r.get('dagger_round', 0)} | {r['windows']:,} | {r['fitted']:,} | "
            f"{r['epochs']:g} | {r['samples']:,} | "
            f"{r['fit_seconds']:.0f} | {r['rmse']:.4f} | {r['hold']:.4f} | {r['repeat']:.4f} | {r['r2']:.2f} | "
            f"{r['r2_typical']:.2f} | {r['r2_seen']:.2f} | {r['moved']:.2f} | {100 * r['share']:.1f} % | "
            f"{r['pos_err_cm']:.1f} | {100 * r['survival']:.0f} | {r['pearson']:.2f} |"
        )
    emit(written=str(write_report(args.out, lines)))


if __name__ == "__main__":
    main()
