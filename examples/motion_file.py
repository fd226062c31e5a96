"""Your own motion file: edit a target trajectory in numpy, save it, and co-design an arm for it.

    python examples/motion_file.py [--out DIR] [--budget 32] [--seed 0]

The motion is the library's toss followed by the same toss played backwards (a throw and
the return), sped up by a third by saving its 50 Hz samples as if taken every 0.015 s: tt
resamples every file to its 50 Hz. Any (T, 3) positions [m] and (T, 4) unit quaternions (w, x, y, z) work the same way;
reading the file places its start over the robot's base. Batched CMA-ES then tries
`--budget` ViperX designs on it, and the oracle (MuJoCo C + mink) compares the winner with
the nominal ViperX. About 15 s on a 2-core CPU. Writes only into --out (default: a new
temporary folder). The same on the command line:

    tt optimize --space viperx --motion there_and_back.npz --method cmaes --budget 32
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np

import tt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="folder for the motion file (default: a new temporary folder)")
    parser.add_argument("--budget", type=int, default=32, help="candidate designs CMA-ES tries")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="tt_motion_"))
    out.mkdir(parents=True, exist_ok=True)

    toss = tt.motion("toss")  # pos (T, 1, 3) [m], quat (T, 1, 4), 50 Hz
    pos = np.concatenate([toss.pos[:, 0], toss.pos[::-1, 0]])  # there and back
    quat = np.concatenate([toss.quat[:, 0], toss.quat[::-1, 0]])
    path = out / "there_and_back.npz"
    tt.save_motion(path, pos, quat, dt=0.015, name="there_and_back")

    motion = tt.motion(path)  # a Path (or a string naming an existing file) reads the file
    print(f"wrote {path}: {len(pos)} samples at 0.015 s, read back as {motion.steps} steps at 50 Hz")

    best = tt.optimize("viperx", [motion], "tracking", method="cmaes", budget=args.budget, seed=args.seed)
    nominal = tt.get_space("viperx").nominal()
    check = tt.validate([nominal, best.best], [motion], "tracking")  # the oracle
    print(f"{'design':<9} {'oracle reward':>14} {'pos err (cm)':>13} {'survival':>9}")
    for i, name in enumerate(("nominal", "cmaes")):
        m = check.metrics
        print(f"{name:<9} {check.reward[i, 0]:>14.2f} {m['pos_err'][i, 0]:>13.2f} {100 * m['survival'][i, 0]:>8.0f}%")


if __name__ == "__main__":
    main()
