"""Quickstart: co-design a ViperX arm for the toss motion, then check the winner on the oracle.

    python examples/quickstart.py [--budget 16] [--seed 0] [--json OUT.json]

Random search and batched CMA-ES each try `--budget` candidate designs, scored by tt's
batched Warp rollouts; the best of the two is re-run on the oracle (MuJoCo C + mink), and the
table compares them. The same job on the command line:

    tt optimize --space viperx --motion toss --method random --budget 16 --seed 0
    tt optimize --space viperx --motion toss --method cmaes --budget 16 --seed 0
"""

import argparse
import json

import tt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budget", type=int, default=16, help="candidate designs per method")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="also write each method's winner (the design and its objective) here")
    args = parser.parse_args()

    space = tt.get_space("viperx")
    toss = tt.motion("toss")  # a library motion; tt.motion("my_motion.npz") reads a file
    results = {
        method: tt.optimize(space.name, [toss], "tracking", method=method, budget=args.budget, seed=args.seed)
        for method in ("random", "cmaes")
    }

    # Each winner on the oracle: the reference every tt result is validated on.
    winners = [r.best for r in results.values()]
    check = tt.validate(winners, [toss], "tracking")
    print(f"{space.name}, {toss.name}, tracking reward; budget {args.budget}, seed {args.seed}")
    print(
        f"{'method':<8} {'objective':>10} {'oracle reward':>14} {'pos err (cm)':>13} {'survival':>9} "
        f"{'optimize (s)':>13}"
    )
    for i, (method, r) in enumerate(results.items()):
        m = check.metrics
        print(
            f"{method:<8} {r.best_reward:>10.2f} {check.reward[i, 0]:>14.2f} {m['pos_err'][i, 0]:>13.2f} "
            f"{100 * m['survival'][i, 0]:>8.0f}% {r.seconds:>13.2f}"
        )
    best = max(range(len(winners)), key=lambda i: check.reward[i, 0])
    print(f"winner: {list(results)[best]}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {
                    method: {"design": space.to_dict(r.best), "objective": float(r.best_reward)}
                    for method, r in results.items()
                },
                f,
                indent=1,
            )


if __name__ == "__main__":
    main()
