"""A short training run: train a tiny DiT for a few steps on CPU, then sample designs from it.

    python examples/train_small.py [--out DIR] [--data DATASET] [--steps 20] [--online]

Trains the "tiny" model on the motion-to-robot and design-to-dynamics tasks (robot+dynamics:
a generator that is also a critic) on a small dataset (`--data`, e.g. from
examples/small_dataset.py; default: 8 designs generated here), or with `--online` on
episodes the simulator generates as training goes. Then it loads the checkpoint to propose
four designs for the toss (Zeroth-Order with simulator verification) and to predict the
winner's reward without simulating, and writes the winner to best.json. Twenty steps teach
the model little: this shows the plumbing (the shipped checkpoints trained for tens of
minutes: checkpoints/README.md). About a minute on a 2-core CPU. Writes only into --out
(default: a new temporary folder). On the command line:

    tt train --data data/small --task robot+dynamics --size tiny --steps 20 --batch-size 8 --out runs/tiny
    tt optimize --motion toss --method zeroth-sim --checkpoint runs/tiny --budget 4 --num-steps 5
"""

import argparse
import json
import tempfile
from pathlib import Path

import tt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="folder for the dataset and run (default: a new temporary folder)")
    parser.add_argument("--data", type=Path, help="a dataset from tt generate (default: generate 8 designs)")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--online", action="store_true", help="train on freshly simulated episodes instead")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="tt_train_"))
    short = dict(min_steps=20, max_motion_steps=60)  # 1.2 s motions, to keep it quick
    data, online = args.data, None
    if args.online:
        online = dict(space="viperx", designs=8, motions=2, refresh_every=10, **short)
    elif data is None:
        data = out / "data"
        tt.generate_dataset("viperx", 8, data, episodes_per_design=2, designs_per_shard=4, progress=False, **short)

    run = tt.train(
        data, out / "run", online=online, task="robot+dynamics", size="tiny", steps=args.steps, batch_size=8,
        checkpoint_every=args.steps, device="cpu", progress=False,
    )  # fmt: skip
    print(f"trained {run.step} steps ({run.parameters:,} parameters), loss {run.losses[0]:.3f} -> {run.losses[-1]:.3f}")
    print(f"checkpoint: {run.checkpoint}")

    toss = tt.motion("toss")
    best = tt.optimize(
        "viperx", [toss], method="zeroth-sim", checkpoint=run.checkpoint, budget=4, num_steps=5, device="cpu"
    )
    guess = tt.predict([best.best], [toss], checkpoint=run.checkpoint, num_steps=5, device="cpu")
    print(f"sampled {best.rollouts} designs in {best.seconds:.1f} s; the best, discrete choices {best.best.discrete},")
    print(f"tracks the toss with reward {best.best_reward:.1f} simulated, {guess.reward[0, 0]:.1f} predicted")
    design = {"design": tt.get_space("viperx").to_dict(best.best), "objective": float(best.best_reward)}
    (out / "best.json").write_text(json.dumps(design, indent=1))  # a design file: tt validate --design best.json


if __name__ == "__main__":
    main()
