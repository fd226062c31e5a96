"""What predicts DiffIK's next command? Linear probes on fresh ViperX control windows.

The control task asks the DiT for the command of the step after the current state (window
slot 1). This fits, per joint, a least-squares line from a few features of the window's
current step to two targets, on one half of the windows, and reports the other half's R^2
against predicting 0:

* the next command's offset from the current joint position (what a delta action anchored
  on the joints must learn; 0 is "hold the current position"), and
* its offset from the last command (what a delta action anchored on the last command must
  learn; 0 is "repeat the last command").

Features: the last command minus the current position (c0 - q), the joint velocity, the end
effector's position error to the look-ahead target, and cos / sin of the joint angles. It
also prints each target's spread (RMS and median of its magnitude): both are heavy-tailed.

Usage: ``python benchmarks/control_probe.py [--windows 4096] [--seed 3]``; writes
``benchmarks/results/control_probe.md``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from machine import machine_header  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def probe(X: np.ndarray, y: np.ndarray) -> float:
    """Held-out R^2 (second half) of a least-squares fit on the first half, against predicting 0."""
    half = len(y) // 2
    w, *_ = np.linalg.lstsq(X[:half], y[:half], rcond=None)
    return float(1 - np.mean((X[half:] @ w - y[half:]) ** 2) / np.mean(y[half:] ** 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--windows", type=int, default=4096, help="control windows (8 consecutive steps)")
    parser.add_argument("--seed", type=int, default=3, help="online refresh seed (designs and motions)")
    parser.add_argument("--out", default=str(RESULTS / "control_probe.md"))
    args = parser.parse_args()
    from tt.dit.online import OnlineConfig, OnlineTokenSource
    from tt.sim.controller import IKConfig

    src = OnlineTokenSource(OnlineConfig(space="viperx", seed=args.seed, action_noise=0.0), device="cpu")
    n = args.windows
    raw = src.sample(n, 8, "consecutive", torch.Generator().manual_seed(0))
    P = raw.values["control"].shape[1] // 8
    c = raw.values["control"].reshape(n, 8, P).double().numpy()
    real = raw.mask["control"].reshape(n, 8, P).numpy()
    joints = raw.values["dyna_joint_obs"].reshape(n, 8, -1, 2)[:, 0, :P].double().numpy()
    q, qvel = joints[..., 0], joints[..., 1]
    ee = raw.values["track_link_obs"].reshape(n, 8, -1, 12)[:, 0, 0, :3].double().numpy()
    lead = 1 + IKConfig().lookahead_steps  # the target DiffIK aims the slot-1 command at
    err = raw.values["target_pose"].reshape(n, 8, -1, 12)[:, lead, 0, :3].double().numpy() - ee
    ones = np.ones((n, 1))
    features = {
        "c0 - q": [c[:, 0] - q],
        "joint velocity": [qvel],
        "c0 - q, velocity": [c[:, 0] - q, qvel],
        "end-effector position error": [err],
        "all of the above, cos / sin q": [c[:, 0] - q, qvel, err, np.cos(q), np.sin(q)],
    }
    targets = {
        "next command - current position (joints anchor)": c[:, 1] - q,
        "next command - last command (command anchor)": c[:, 1] - c[:, 0],
    }
    ok = real[:, 1] & real[:, 0]
    lines = [
        "# What predicts DiffIK's next command (linear probes, ViperX)",
        "",
        machine_header("cpu").rstrip(),
        f"- command: `python benchmarks/control_probe.py {' '.join(sys.argv[1:])}`",
        f"- {n} windows of fresh episodes (`tt.dit.online` refresh 0, seed {args.seed}, no control perturbation, "
        f"{len(src)} episodes); per joint slot, a least-squares fit on half the windows, R^2 on the other half "
        "against predicting 0; look-ahead target: window step " + str(lead),
        "",
    ]
    for tname, y in targets.items():
        lines += [
            f"## {tname}",
            "",
            "| features | " + " | ".join(f"joint {i}" for i in range(P)) + " |",
            "|---|" + "---:|" * P,
        ]
        for fname, f in features.items():
            X = np.concatenate(f + [ones], 1)
            r2 = [probe(X[ok[:, i]], y[ok[:, i], i]) for i in range(P)]
            lines.append(f"| {fname} | " + " | ".join(f"{v:.2f}" for v in r2) + " |")
        rms = [np.sqrt(np.mean(y[ok[:, i], i] ** 2)) for i in range(P)]
        med = [np.median(np.abs(y[ok[:, i], i])) for i in range(P)]
        lines += [
            "| RMS (rad) | " + " | ".join(f"{v:.4f}" for v in rms) + " |",
            "| median magnitude (rad) | " + " | ".join(f"{v:.4f}" for v in med) + " |",
            "",
        ]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
