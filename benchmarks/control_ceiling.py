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

Usage: ``python benchmarks/control_ceiling.py [--rows 16384x20 65536x20 262144x20 98304x1]`` (training
windows x epochs per row; the last row sees about the DiT's 96,000 windows);
writes ``benchmarks/results/control_ceiling.md``.
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

#: Steps of a control window (the DiT's layout).
STEPS = 8


def emit(**fields) -> dict:
    print(json.dumps({"bench": "control_ceiling", **fields}), flush=True)
    return fields


def features(tokens, layout) -> torch.Tensor:
    """(n, F) float32: the control query's clean conditions of normalised windows `tokens`
    (padding at PAD_VALUE, as the DiT reads it): every embodiment token, step 0 of every
    per-step type (the current state and the last command) and the target poses of all steps."""
    from tt.tokens.schema import STEP_ROLES

    parts = []
    for s in layout.specs:
        v = tokens.values[s.name].float()
        n = v.shape[0]
        if s.role not in STEP_ROLES:
            parts.append(v.reshape(n, -1))
        elif s.name == "target_pose":
            parts.append(v.reshape(n, -1))
        else:
            parts.append(v.reshape(n, layout.steps, -1)[:, 0])
    return torch.cat(parts, 1)


def commands(raw, layout) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Raw windows -> (c0, c1, real): the last and next commands (n, P) [rad] and the joint
    slots both are real in (n, P)."""
    P = layout["control"].per_step
    n = raw.values["control"].shape[0]
    c = raw.values["control"].reshape(n, layout.steps, P).float()
    m = raw.mask["control"].reshape(n, layout.steps, P)
    return c[:, 0], c[:, 1], m[:, 0] & m[:, 1]


class Regressor(torch.nn.Module):
    """MLP: features -> the next command's offset from the last, in units of `scale` (P,)."""

    def __init__(self, width_in: int, joints: int, scale: torch.Tensor, mean: torch.Tensor, std: torch.Tensor,
                 hidden: int = 512, depth: int = 3):
        super().__init__()
        layers, w = [], width_in
        for _ in range(depth):
            layers += [torch.nn.Linear(w, hidden), torch.nn.GELU()]
            w = hidden
        layers.append(torch.nn.Linear(w, joints))
        self.net = torch.nn.Sequential(*layers)
        self.register_buffer("scale", scale)
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(n, F) features -> (n, P) offsets [rad]."""
        return self.net((x - self.mean) / self.std) * self.scale


def draw_windows(source, n: int, layout, norm, seed: int, chunk: int = 8192, refreshes: int = 1):
    """n raw windows of `source` -> (features (n, F), c0, c1, real, q (n, P)), an equal share
    from each of its first `refreshes` online refreshes (one held at a time, so memory stays
    one refresh's), in a random order."""
    from tt.dit.tasks import CONTROL, task_windows

    gen = torch.Generator().manual_seed(seed)
    X, C0, C1, R, Q = [], [], [], [], []
    shares = [n // refreshes + (k < n % refreshes) for k in range(refreshes)]
    draws = []
    for k, share in enumerate(shares):
        if refreshes > 1:
            source.start_step(k * source.config.refresh_every)
        for a in range(0, share, chunk):
            draws.append(task_windows(source, layout, min(chunk, share - a), CONTROL, gen))
    for raw in draws:
        X.append(features(norm.normalize(raw), layout))
        c0, c1, real = commands(raw, layout)
        P = c0.shape[1]
        Q.append(raw.values["dyna_joint_obs"].reshape(len(c0), layout.steps, -1, 2)[:, 0, :P, 0].float())
        C0.append(c0), C1.append(c1), R.append(real)
    order = torch.randperm(n, generator=gen)
    return tuple(torch.cat(x)[order] for x in (X, C0, C1, R, Q))


def fit(X, c0, c1, real, *, epochs: int, batch: int, lr: float, seed: int) -> tuple[Regressor, list[float]]:
    """Masked MSE on the offsets in units of each joint slot's RMS offset; AdamW, cosine schedule."""
    torch.manual_seed(seed)
    y = torch.where(real, c1 - c0, torch.zeros_like(c0))
    scale = (y.pow(2).sum(0) / real.sum(0).clamp_min(1)).sqrt().clamp_min(1e-4)
    mean, std = X.mean(0), X.std(0).clamp_min(1e-3)
    model = Regressor(X.shape[1], c0.shape[1], scale, mean, std)
    steps = max(1, int(epochs * len(X) // batch))
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.05)
    gen = torch.Generator().manual_seed(seed)
    losses = []
    for k in range(steps):
        i = torch.randint(0, len(X), (batch,), generator=gen)
        m = real[i].float()
        err = (model(X[i]) - y[i]) / model.scale
        loss = (err.pow(2) * m).sum() / m.sum().clamp_min(1)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
    return model.eval(), losses


def one_step(model, X, c0, c1, real, q) -> dict:
    """RMSE [rad] of the next command: the regressor's, holding the current joints', repeating the last command's."""
    with torch.no_grad():
        pred = c0 + model(X)
    rmse = lambda e: float(e[real].pow(2).mean().sqrt())  # noqa: E731
    y = (c1 - c0)[real]
    return {"rmse": rmse(pred - c1), "hold": rmse(q - c1), "repeat": rmse(c0 - c1),
            "r2": float(1 - ((pred - c1)[real]).pow(2).mean() / y.pow(2).mean())}


def regressor_policy(model: Regressor, layout, norm):
    """A closed-loop policy (`tt.dit.closed_loop.Policy`) that builds the DiT controller's query
    (`ModelPolicy.query`) and executes the last command plus the regressor's offset."""
    from tt.dit.checkpoint import TrainedModel
    from tt.dit.policies import ModelPolicy

    class RegressorPolicy(ModelPolicy):
        def __call__(self, step, worlds, state):
            tokens, slot = self.query(step, worlds, state)
            c0 = self.control_slot(tokens, 0)  # the last command (given: step 0 of the window)
            with torch.no_grad():
                target = c0 + model(features(tokens, self.layout)) if slot == 1 else c0
            return self.commands(worlds, state, target)

    return RegressorPolicy(TrainedModel(model=model, normalizer=norm, layout=layout, step=0, space=SPACE, tasks=("control",)))


class Repeat:
    """The still arm: every step repeats the last command (the start posture's), what a
    controller that learned no increment does (`dit_control.md`)."""

    def reset(self, ctx) -> None:
        pass

    def __call__(self, step, worlds, state):
        return state.ctrl[worlds].clone()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", nargs="+", default=["16384x20", "65536x20", "262144x20", "98304x1"],
                        help="one row per WINDOWSxEPOCHS: the first WINDOWS training windows, EPOCHS passes over them")
    parser.add_argument("--refreshes", type=int, default=16, help="online refreshes (64 new designs x 4 motions each) "
                        "the training windows are drawn from: the designs seen")
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0, help="training data and MLP seed")
    parser.add_argument("--design-seed", type=int, default=20261122, help="held-out designs and one-step windows")
    parser.add_argument("--designs", type=int, default=25, help="held-out designs of the closed loop")
    parser.add_argument("--motions", type=int, default=5, help="validation motions of the closed loop")
    parser.add_argument("--test-windows", type=int, default=4096, help="one-step windows of held-out designs")
    parser.add_argument("--out", default=str(RESULTS / "control_ceiling.md"))
    args = parser.parse_args()
    try:
        plan = [(int(w), float(e)) for w, _, e in (r.partition("x") for r in args.rows)]
    except ValueError:
        parser.error(f"--rows {args.rows}: each row is WINDOWSxEPOCHS, e.g. 65536x20")
    if any(w < 1 or not e > 0 for w, e in plan):
        parser.error(f"--rows {args.rows}: windows must be >= 1 and epochs > 0")
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from tt.baselines.evaluate import score_episode
    from tt.dit.closed_loop import closed_loop_rollout
    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.dit.policies import IKPolicy
    from tt.sim.designs import get_space
    from tt.sim.validate import oracle_rollout

    load_before, started = os.getloadavg(), time.perf_counter()
    # The DiT's training data: tt generate's draws, control perturbation included.
    cfg = OnlineConfig(space=SPACE, seed=args.seed, refresh_every=1, buffer=1)
    train_src = OnlineTokenSource(cfg, device="cpu")
    layout, norm = train_src.layout(STEPS), train_src.fit_normalizer()
    test_src = OnlineTokenSource(OnlineConfig(space=SPACE, seed=args.design_seed, action_noise=0.0), device="cpu")
    Xt, c0t, c1t, realt, qt = draw_windows(test_src, args.test_windows, layout, norm, args.seed + 1)

    space = get_space(SPACE)
    designs = space.sample(args.designs, seed=args.design_seed)
    motions = cut(validation_motions(args.motions), 0)
    t = time.perf_counter()
    r_oracle, m_oracle = score_episode(oracle_rollout(designs, motions), designs, motions, "tracking")
    emit(oracle_reward=float(r_oracle.mean()), seconds=time.perf_counter() - t)
    r_ik, m_ik = score_episode(closed_loop_rollout(designs, motions, IKPolicy()), designs, motions, "tracking")
    emit(ik_share=float(r_ik.mean() / r_oracle.mean()))
    r_still, m_still = score_episode(closed_loop_rollout(designs, motions, Repeat()), designs, motions, "tracking")
    emit(repeat_share=float(r_still.mean() / r_oracle.mean()))

    rows = []
    t = time.perf_counter()
    X, c0, c1, real, _ = draw_windows(train_src, max(w for w, _ in plan), layout, norm, args.seed, refreshes=args.refreshes)
    # Other windows of the training designs (another draw of the last refresh's episodes):
    # generalising to new windows of designs seen, against generalising to new designs.
    seen = draw_windows(train_src, args.test_windows, layout, norm, args.seed + 2)
    gen_s = time.perf_counter() - t
    emit(episodes=train_src.stats["episodes"], generate_seconds=gen_s)
    for n, epochs in plan:
        t = time.perf_counter()
        model, losses = fit(X[:n], c0[:n], c1[:n], real[:n], epochs=epochs, batch=args.batch, lr=args.lr, seed=args.seed)
        fit_s = time.perf_counter() - t
        step = one_step(model, Xt, c0t, c1t, realt, qt)
        step["r2_seen"] = one_step(model, *seen)["r2"]
        t = time.perf_counter()
        ep = closed_loop_rollout(designs, motions, regressor_policy(model, layout, norm))
        loop_s = time.perf_counter() - t
        r, m = score_episode(ep, designs, motions, "tracking")
        rows.append(emit(windows=n, epochs=epochs, samples=len(losses) * args.batch, fit_seconds=fit_s, loss=float(np.mean(losses[-50:])),
                         **step, share=float(r.mean() / r_oracle.mean()), pos_err_cm=float(np.nanmean(m["pos_err"])),
                         survival=float(np.mean(m["survival"])), pearson=pearson(r_oracle.ravel(), r.ravel()),
                         loop_seconds=loop_s))
    load_after = os.getloadavg()
    lines = [
        "# A supervised ceiling for the control task (ViperX)",
        "",
        machine_header("cpu").rstrip(),
        f"- torch threads {torch.get_num_threads()}; load average (1 min) before / after: {load_before[0]:.1f} / "
        f"{load_after[0]:.1f}; {time.perf_counter() - started:.0f} s in all",
        f"- command: `python benchmarks/control_ceiling.py {' '.join(sys.argv[1:])}`",
        f"- training windows: 8 consecutive steps of {train_src.stats['episodes']} episodes of "
        f"{args.refreshes * cfg.designs} designs ({args.refreshes} online refreshes of {cfg.designs} designs x "
        f"{cfg.motions} motions, seed {args.seed}, control perturbation {cfg.action_noise}; {gen_s:.0f} s to generate and "
        "draw), an equal share from each refresh in a random order, the first N of that draw per row; features: the DiT control query's clean "
        f"conditions ({X.shape[1]} values: embodiment, step 0's state and command, 8 target poses), normalised as the "
        f"DiT reads them; MLP 3 x 512 (GELU), batch {args.batch}, AdamW lr {args.lr:g} one-cycle; "
        "target: the next command minus the last, masked MSE per joint in units of its RMS",
        f"- one step: {args.test_windows} windows of fresh episodes of other designs (online refresh 0, seed "
        f"{args.design_seed}, no perturbation), as `dit_control.md`'s",
        f"- closed loop: {len(designs)} held-out ViperX designs (`space.sample({args.designs}, seed={args.design_seed})`) x "
        f"{len(motions)} validation motions ({', '.join(m.name for m in motions)}), Warp physics; oracle (MuJoCo C + mink) "
        f"mean tracking reward {r_oracle.mean():.1f}, pos err {np.nanmean(m_oracle['pos_err']):.1f} cm, survival "
        f"{100 * np.mean(m_oracle['survival']):.0f} %; DiffIK in the same closed loop (the teacher): "
        f"{100 * r_ik.mean() / r_oracle.mean():.1f} % of the oracle, pos err {np.nanmean(m_ik['pos_err']):.1f} cm; "
        f"repeating the start posture's command every step (a still arm): {100 * r_still.mean() / r_oracle.mean():.1f} %, "
        f"pos err {np.nanmean(m_still['pos_err']):.1f} cm, survival {100 * np.mean(m_still['survival']):.0f} %",
        "- targets (issue 17, for the DiT): >= 50 % of the oracle's reward; one-step RMSE <= half of holding's",
        "",
        "| training windows | epochs | samples seen | fit (s) | one-step RMSE (rad) | hold RMSE | repeat RMSE | R^2 of the offset, held-out designs "
        "| R^2, training designs' other windows | share of oracle reward | pos err (cm) | survival (%) | r vs oracle |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['windows']:,} | {r['epochs']:g} | {r['samples']:,} | {r['fit_seconds']:.0f} | {r['rmse']:.4f} | {r['hold']:.4f} | "
                     f"{r['repeat']:.4f} | {r['r2']:.2f} | {r['r2_seen']:.2f} | {100 * r['share']:.1f} % | {r['pos_err_cm']:.1f} | "
                     f"{100 * r['survival']:.0f} | {r['pearson']:.2f} |")
    emit(written=str(write_report(args.out, lines)))


if __name__ == "__main__":
    main()
