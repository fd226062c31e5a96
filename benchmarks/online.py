"""Online training (``tt train --online``) against training from a dataset, side by side.

The same model (the shipped checkpoint's size, mini, both tasks), batch and steps, in one
process: once reading windows from a `tt generate` dataset folder, once from
`tt.dit.online.OnlineTokenSource`, which rolls out new designs with the batched Warp sim
every `refresh_every` steps. Reports wall time per step for both, and how the online run's
time splits between generating (rollout + tokenization) and the network. Writes
``benchmarks/results/online.md``.

Usage: ``python benchmarks/online.py --data DATASET [--steps 120] [--refresh-every 40]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

from tt.dit.online import OnlineConfig, OnlineTokenSource  # noqa: E402
from tt.dit.train import TrainConfig, train  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "online.md"


def run(source, args, label: str) -> dict:
    with tempfile.TemporaryDirectory() as out:
        cfg = TrainConfig(
            out=out,
            task="both",
            size=args.size,
            steps=args.steps,
            batch_size=args.batch_size,
            device="cpu",
            checkpoint_every=10**9,
            resume=False,
            warmup_steps=10,
        )
        t0 = time.perf_counter()
        result = train(cfg, episodes=source)
        wall = time.perf_counter() - t0
    return {"label": label, "wall": wall, "per_step": wall / args.steps, "loss": float(result.losses[-10:].mean())}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="dataset folder written by `tt generate` (ViperX)")
    p.add_argument("--steps", type=int, default=120)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--size", default="mini")
    p.add_argument("--designs", type=int, default=64)
    p.add_argument("--motions", type=int, default=4)
    p.add_argument("--refresh-every", type=int, default=40)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default=str(RESULTS))
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    from tt.dit.loader import open_token_source

    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    stored = run(open_token_source(args.data), args, "dataset")
    online_cfg = OnlineConfig(
        space="viperx", designs=args.designs, motions=args.motions, refresh_every=args.refresh_every
    )
    source = OnlineTokenSource(online_cfg, device="cpu")
    source.fit_normalizer()  # refresh 0 (and the Warp kernel compile) before timing
    gen0 = source.stats["seconds"]
    online = run(source, args, "online")
    gen = source.stats["seconds"] - gen0
    refreshes = source.stats["refreshes"] - 1
    total = time.perf_counter() - t0
    lines = [
        "# Online training vs a dataset (CPU)",
        "",
        machine_header("cpu").rstrip(),
        f"- torch threads {args.threads}; load average (1 min) before / after: {load0:.1f} / "
        f"{os.getloadavg()[0]:.1f}; wall {total:.0f} s",
        f"- command: `python benchmarks/online.py --data {args.data} --steps {args.steps} --batch-size "
        f"{args.batch_size} "
        f"--refresh-every {args.refresh_every} --designs {args.designs} --motions {args.motions}`",
        "",
        f"Model {args.size}, task both, batch {args.batch_size}, {args.steps} steps each, one process. Online: "
        f"{args.designs} ViperX designs x {args.motions} augmented training motions per refresh, a refresh every "
        f"{args.refresh_every} steps (refresh 0, with the Warp kernel compile, made before timing), the last "
        f"{online_cfg.buffer} refreshes buffered.",
        "",
        "| source | wall (s) | s / step | steps / s | generation (s) | share generating |",
        "|---|---:|---:|---:|---:|---:|",
        f"| dataset `{Path(args.data).name}` | {stored['wall']:.1f} | {stored['per_step']:.3f} | "
        f"{1 / stored['per_step']:.2f} | - | - |",
        f"| online ({refreshes} refreshes) | {online['wall']:.1f} | {online['per_step']:.3f} | "
        f"{1 / online['per_step']:.2f} | "
        f"{gen:.1f} | {100 * gen / online['wall']:.0f} % |",
        "",
        f"Online / dataset time per step: {online['per_step'] / stored['per_step']:.2f}x. Per refresh: "
        f"{gen / max(refreshes, 1):.1f} s for {source.stats['world_steps'] / source.stats['refreshes']:.0f} "
        "world-steps "
        f"simulated and tokenized on average ({source.stats['dropped']} of "
        f"{source.stats['episodes'] + source.stats['dropped']} episodes dropped as shorter than "
        f"{online_cfg.min_steps} steps, as `tt generate` drops them). The losses are not comparable (different data).",
        "",
    ]
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
