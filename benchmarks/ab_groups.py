"""A/B of `tt.sim.rollout.GROUPS_AT_ONCE`: 4,096 random ViperX designs (3 topology groups) on
the toss through `tt.sim.rollout.rollout` (tree fields built once, setup included in each
timing), 1 thread, and 2 threads with the groups one after another or at once on a shared
pool, interleaved, 5 repeats each.

Writes benchmarks/results/ab_groups.md. Usage: ``python benchmarks/ab_groups.py``.
"""

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

import tt.sim.rollout as sr  # noqa: E402
from tt.sim.designs import get_space  # noqa: E402
from tt.sim.motions import for_space, get_motion  # noqa: E402

REPEATS, N = 5, 4096
#: (label, threads, GROUPS_AT_ONCE)
SETTINGS = (
    ("1 thread", 1, True),
    ("2 threads, groups one after another", 2, False),
    ("2 threads, groups at once", 2, True),
)


def main() -> None:
    sp = get_space("viperx")
    trees = sp.trees(sp.sample(N, seed=0))
    motions = for_space([get_motion("toss")], "viperx")
    sr.rollout(trees, motions, threads=2)  # compile / cache load
    seconds: dict[str, list[float]] = {}
    for _ in range(REPEATS):
        for label, threads, at_once in SETTINGS:
            sr.GROUPS_AT_ONCE = at_once
            t = time.perf_counter()
            sr.rollout(trees, motions, threads=threads)
            seconds.setdefault(label, []).append(time.perf_counter() - t)
            print(label, round(seconds[label][-1], 2), flush=True)
    lines = [
        "# A/B: a threaded rollout's topology groups one after another or at once",
        "",
        machine_header(),
        "",
        f"- command: `python benchmarks/ab_groups.py`; {N} random ViperX designs (seed 0, {len(trees.groups)} "
        f"topology groups) x toss, `tt.sim.rollout.rollout` on tree fields (setup included), {REPEATS} "
        "interleaved repeats",
        "",
        "| setting | runs (s) | fastest (s) | median (s) | 1 -> 2 threads (fastest / median) |",
        "|---|---|---:|---:|---:|",
    ]
    one = seconds[SETTINGS[0][0]]
    for label, _, _ in SETTINGS:
        ts = seconds[label]
        speedup = "" if ts is one else f"{min(one) / min(ts):.2f}x / {np.median(one) / np.median(ts):.2f}x"
        lines.append(
            f"| {label} | {', '.join(f'{t:.2f}' for t in ts)} | {min(ts):.2f} | {np.median(ts):.2f} | {speedup} |"
        )
    out = Path(__file__).parent / "results" / "ab_groups.md"
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
