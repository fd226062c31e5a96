"""A supervised ceiling for the model as a critic: a plain regressor, no diffusion.

It learns the simulated tracking reward straight from what the DiT's motion-to-robot query
is given: the robot's embodiment tokens (tokenized, padded to the space's largest robot,
flattened, standardised) and the target poses at the query's 8 evenly placed steps
(`tt.guidance.predicted.query_steps`: position and rotation matrix), plus the motion length.
Training pairs are the episodes a ``tt train --online`` run draws (`tt.dit.online`:
refreshes 0 .. R-1, each ``--online-designs`` designs x ``--online-motions`` augmented
training motions; simulated here without the control perturbation); the evaluation set is
the ladder's (`tt.ladder.heldout_designs` x `tt.ladder.validation_motions`), the same pairs
`benchmarks/dit_ladder.py` scores a checkpoint on. The regressor is a torch MLP (two
hidden layers, SiLU) fit to reward / T by MSE with Adam, the epoch kept by a 10 % split of
the training designs. It separates what the data allows from what diffusion training
achieves: pooled Pearson r and mean within-motion r on the held-out set.

Usage: ``python benchmarks/dit_ceiling.py [--space viperx-nominal] [--refreshes 16] [--designs 64]
[--motions 4] [--heldout 32] [--val-motions 5]``. Prints one JSON line; writes
``benchmarks/results/dit_ceiling_<space>.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def features(space, designs, motions, steps: int = 8) -> np.ndarray:
    """(D * M, F) features, design-major: embodiment tokens of each design, then the motion's
    target poses at the query's `steps` even steps and its length T / 1000."""
    import warnings

    from tt.dit.layout import Role, layout_from_schema
    from tt.guidance.predicted import query_steps
    from tt.kernels.rotations import quat_to_mat
    from tt.tokens.draws import space_token_maxima
    from tt.tokens.tokenize import Tokenizer, TokenizeWarning

    layout = layout_from_schema({k: v for k, v in space_token_maxima(space.name)["maxima"].items() if v > 0})
    static = [s for s in layout.specs if s.role is Role.EMBODIMENT]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TokenizeWarning)
        emb = Tokenizer()([space.model(d) for d in designs])
    padded = emb.tokens.pad_to({s.name: s.length for s in static})
    robot = np.concatenate(
        [
            np.where(np.asarray(padded.mask[s.name])[..., None], np.asarray(padded.values[s.name]), 0.0).reshape(
                len(designs), -1
            )
            for s in static
        ]
        + [np.asarray(padded.mask[s.name], np.float64) for s in static],
        axis=1,
    )
    per_motion = []
    for m in motions:
        st = query_steps(m.steps, steps, 1)[0].numpy()
        pos = m.pos[st].reshape(steps, -1)
        rot = quat_to_mat(m.quat[st]).reshape(steps, -1)
        per_motion.append(np.concatenate([pos.ravel(), rot.ravel(), [m.steps / 1000.0]]))
    motion = np.stack(per_motion)
    D, M = len(designs), len(motions)
    return np.concatenate([np.repeat(robot, M, axis=0), np.tile(motion, (D, 1))], axis=1).astype(np.float64)


def simulate(designs, motions, reward: str) -> np.ndarray:
    from tt.baselines.evaluate import evaluate_designs

    # The space's own backend: tt's kernels, or mjbatch for contacts (the quadruped).
    return evaluate_designs(designs, motions, reward, device="cpu").reward  # (D, M)


def fit_mlp(
    x: np.ndarray,
    y: np.ndarray,
    groups: np.ndarray,
    *,
    hidden: int,
    epochs: int,
    lr: float,
    weight_decay: float,
    seed: int,
):
    """MLP on standardised x -> y; the epoch with the lowest MSE on 10 % of the groups (designs) is kept."""
    rng = np.random.default_rng(seed)
    ids = np.unique(groups)
    val_ids = rng.choice(ids, size=max(1, len(ids) // 10), replace=False)
    val = np.isin(groups, val_ids)
    mu, sd = x[~val].mean(0), x[~val].std(0) + 1e-6
    ym, ys = y[~val].mean(), y[~val].std() + 1e-9
    xt = torch.as_tensor((x - mu) / sd, dtype=torch.float32)
    yt = torch.as_tensor((y - ym) / ys, dtype=torch.float32)
    torch.manual_seed(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(x.shape[1], hidden),
        torch.nn.SiLU(),
        torch.nn.Linear(hidden, hidden),
        torch.nn.SiLU(),
        torch.nn.Linear(hidden, 1),
    )
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)
    tr, va = torch.as_tensor(~val), torch.as_tensor(val)
    best, state, best_epoch = float("inf"), None, 0
    for epoch in range(epochs):
        perm = torch.randperm(int(tr.sum()))
        xs, ysub = xt[tr][perm], yt[tr][perm]
        for i in range(0, len(xs), 256):
            loss = torch.nn.functional.mse_loss(net(xs[i : i + 256])[:, 0], ysub[i : i + 256])
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            v = float(torch.nn.functional.mse_loss(net(xt[va])[:, 0], yt[va]))
        if v < best:
            best, best_epoch = v, epoch
            state = {k: t.clone() for k, t in net.state_dict().items()}
    net.load_state_dict(state)

    def predict(z: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return net(torch.as_tensor((z - mu) / sd, dtype=torch.float32))[:, 0].double().numpy() * ys + ym

    return predict, {"val_mse": best, "best_epoch": best_epoch}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--space", default="viperx-nominal")
    p.add_argument("--refreshes", type=int, default=16, help="online refreshes whose episodes train the regressor")
    p.add_argument("--designs", type=int, default=64, help="designs per refresh (tt train --config online.designs)")
    p.add_argument("--motions", type=int, default=4, help="motions per refresh (tt train --online-motions)")
    p.add_argument("--seed", type=int, default=0, help="the online run's seed")
    p.add_argument("--heldout", type=int, default=32, help="held-out designs")
    p.add_argument("--val-motions", type=int, default=5)
    p.add_argument("--reward", default="tracking")
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--epochs", type=int, default=300)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.ladder import heldout_designs, pearson, validation_motions, within_motion
    from tt.sim.designs import get_space

    space = get_space(args.space)
    t0 = time.perf_counter()
    src = OnlineTokenSource(
        OnlineConfig(space=args.space, designs=args.designs, motions=args.motions, seed=args.seed), device="cpu"
    )
    xs, ys, groups = [], [], []
    for k in range(args.refreshes):
        designs, motions = src.draw(k)
        r = simulate(designs, motions, args.reward)  # (D, M)
        xs.append(features(space, designs, motions))
        ys.append((r / np.array([m.steps for m in motions])[None, :]).ravel())
        groups.append(np.repeat(np.arange(len(designs)) + k * len(designs), len(motions)))
    x, y, g = np.concatenate(xs), np.concatenate(ys), np.concatenate(groups)
    t1 = time.perf_counter()
    predict, info = fit_mlp(
        x, y, g, hidden=args.hidden, epochs=args.epochs, lr=args.lr, weight_decay=args.weight_decay, seed=args.seed
    )
    t2 = time.perf_counter()
    designs, motions = heldout_designs(args.space, args.heldout), validation_motions(args.space, args.val_motions)
    sim = simulate(designs, motions, args.reward)
    steps = np.array([m.steps for m in motions])[None, :]
    pred = predict(features(space, designs, motions)).reshape(len(designs), len(motions)) * steps
    within = within_motion(pred, sim)
    result = {
        "bench": "dit_ceiling",
        "space": args.space,
        "train_pairs": int(len(y)),
        "heldout_pairs": int(sim.size),
        "pooled_r": pearson(pred, sim),
        "within_r": within,
        "within_r_mean": float(np.nanmean(within)) if np.isfinite(within).any() else float("nan"),
        "train_pooled_r": pearson(predict(x) * 1.0, y),
        **info,
        "seconds": {"simulate_train": t1 - t0, "fit": t2 - t1},
    }
    print(json.dumps(result), flush=True)
    out = Path(args.out) if args.out else RESULTS / f"dit_ceiling_{args.space}.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        "\n".join(
            [
                "# Supervised ceiling: an MLP from embodiment tokens + target poses to the simulated "
                f"{args.reward} reward",
                "",
                machine_header("cpu"),
                f"Training: {len(y)} episodes, refreshes 0..{args.refreshes - 1} of `tt train --online "
                f"--config online.space={args.space} "
                f"--config online.designs={args.designs} --config online.motions={args.motions} --seed {args.seed}`. "
                "Held out: "
                f"{len(designs)} designs (`tt.ladder.heldout_designs`) x {len(motions)} validation motions. MLP "
                f"{args.hidden}x2, {args.epochs} epochs (kept: {info['best_epoch']}).",
                "",
                f"- pooled Pearson r: **{result['pooled_r']:.2f}**",
                f"- mean within-motion r: **{result['within_r_mean']:.2f}** "
                f"({', '.join(f'{m.name} {r:.2f}' for m, r in zip(motions, within))})",
                "",
            ]
        )
    )
    print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
