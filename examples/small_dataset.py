"""A small dataset: generate RoboToken episodes of a few random ViperX designs and read it back.

    python examples/small_dataset.py [--out DIR] [--designs 8] [--episodes-per-design 2]

Each design is rolled out on augmented training motions in one batched Warp rollout, and
every episode that tracks at least `min_steps` steps is tokenized (the design's embodiment
tokens, its states, forces and commands, the targets) and written to checksummed zarr
shards. Generation is resumable: calling it again on the same folder generates only the
shards that are missing. Motions are cut at 60 steps (1.2 s) to keep it quick: about 15 s
on a 2-core CPU. Writes only into --out (default: a new temporary folder). The same on the
command line:

    tt generate --space viperx --designs 8 --episodes-per-design 2 --out data/small \
        --config designs_per_shard=4 --config min_steps=20 --config max_motion_steps=60
    tt dataset info data/small
"""

import argparse
import tempfile
from pathlib import Path

import tt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="dataset folder (default: one in a new temporary folder)")
    parser.add_argument("--designs", type=int, default=8)
    parser.add_argument("--episodes-per-design", type=int, default=2)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="tt_dataset_")) / "small"

    options = dict(
        episodes_per_design=args.episodes_per_design,
        designs_per_shard=4,  # two shards for 8 designs: the unit of resuming and of parallel workers
        min_steps=20,  # keep episodes that track for at least 20 steps (0.4 s)
        max_motion_steps=60,  # cut every training motion at 60 steps
        seed=0,
    )
    print(tt.generate_dataset("viperx", args.designs, out, **options))
    again = tt.generate_dataset("viperx", args.designs, out, progress=False, **options)
    print(again.splitlines()[-1])  # resumed: every shard is there, so nothing to do

    info = tt.dataset_info(out)  # what `tt dataset info --json` prints
    r = info["reward"]
    print(
        f"{out}: {info['space']}, {info['designs']} designs, {info['episodes']} episodes kept of "
        f"{info['episodes_generated']} ({info['steps']} steps, {info['bytes'] / 1024:.0f} KiB), "
        f"{info['shards']} shards, complete: {info['complete']}"
    )
    print(f"episode reward: min {r['min']:.1f}, median {r['p50']:.1f}, max {r['max']:.1f}")


if __name__ == "__main__":
    main()
