"""A/B of `tt.kernels.rollout.SLICES_PER_THREAD`: 4,096 random ViperX designs on the toss through
`tt.sim.rollout.rollout` (tree fields built once, setup included in each timing), 1 and 2
threads, 4 and 16 slices of worlds per thread, interleaved, 3 repeats each.

Writes benchmarks/results/ab_slices.md. Usage: ``python benchmarks/ab_slices.py``.
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

import tt.kernels.rollout as kr  # noqa: E402
from tt.sim.designs import get_space  # noqa: E402
from tt.sim.motions import for_space, get_motion  # noqa: E402
from tt.sim.rollout import rollout  # noqa: E402

SLICES, THREADS, REPEATS, N = (4, 16), (1, 2), 3, 4096


def main() -> None:
    sp = get_space("viperx")
    trees = sp.trees(sp.sample(N, seed=0))
    motions = for_space([get_motion("toss")], "viperx")
    rollout(trees, motions, threads=2)  # compile / cache load
    seconds: dict[tuple[int, int], list[float]] = {}
    for _ in range(REPEATS):
        for spt in SLICES:
            for th in THREADS:
                kr.SLICES_PER_THREAD = spt
                t = time.perf_counter()
                rollout(trees, motions, threads=th)
                seconds.setdefault((spt, th), []).append(time.perf_counter() - t)
                print(spt, th, round(seconds[(spt, th)][-1], 2), flush=True)
    lines = [
        "# A/B: slices of worlds per thread in a threaded rollout",
        "",
        machine_header(),
        "",
        f"- command: `python benchmarks/ab_slices.py`; {N} random ViperX designs (seed 0) x toss, "
        f"`tt.sim.rollout.rollout` on tree fields (setup included), {REPEATS} interleaved repeats",
        "",
        "| slices per thread | threads | runs (s) | fastest (s) | median (s) |",
        "|---:|---:|---|---:|---:|",
    ]
    for (spt, th), ts in sorted(seconds.items()):
        lines.append(f"| {spt} | {th} | {', '.join(f'{t:.2f}' for t in ts)} | {min(ts):.2f} | {np.median(ts):.2f} |")
    # At 1 thread there is one slice whatever the setting: those rows are the same code.
    one = [t for spt in SLICES for t in seconds[(spt, 1)]]
    lines += [
        "",
        f"At 1 thread there is one slice whatever the setting, so those {len(one)} runs time the same code "
        f"({min(one):.2f}-{max(one):.2f} s: the box's spread); the 1 -> 2 thread figures below divide their "
        "fastest and their median by each 2-thread setting's.",
    ]
    for spt in SLICES:
        two = seconds[(spt, 2)]
        lines.append(
            f"- {spt} slices per thread, 2 threads: fastest {min(two):.2f} s ({min(one) / min(two):.2f}x), "
            f"median {np.median(two):.2f} s ({np.median(one) / np.median(two):.2f}x)"
        )
    out = Path(__file__).parent / "results" / "ab_slices.md"
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
