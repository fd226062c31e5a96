"""Bit-identity check for refactors of the simulation stack: record, then compare.

    python benchmarks/reference_rollouts.py record /tmp/tt_ref_before
    ... change the code ...
    python benchmarks/reference_rollouts.py record /tmp/tt_ref_after
    python benchmarks/reference_rollouts.py compare /tmp/tt_ref_before /tmp/tt_ref_after

`record` runs a fixed set of rollouts through the public entry points only (so the same
script runs before and after a change of the layers below them) and saves every array of
every result to one ``.npz`` per case. `compare` demands ``np.array_equal`` (NaNs equal)
on every array of every case and exits non-zero naming the first that differs: a
refactor that only moves code must not change one bit (same device, same machine).

Cases (CPU device):

* ``warp_viperx``: the nominal ViperX and 7 random designs (seed 0: 5-, 6- and 7-DoF
  topologies) on toss and scrub, full length, the "warp" backend (fused kernels);
* ``warp_viperx_noise``: the same with control perturbation (action_noise 0.05);
* ``warp_twoarm``: the nominal aloha, one random aloha and the nominal bimanual on two
  bimanual motions ("warp" backend, two end effectors);
* ``open_loop``: `tt.kernels.simulate` (open-loop dynamics) and
  `tt.kernels.forward_kinematics` of the 8 ViperX designs;
* ``simgrad``: the differentiable rollout's reward and its gradient with respect to the
  nominal ViperX's continuous choices on 12 steps of toss (`tt.guidance.simgrad`);
* ``dit_ik`` / ``dit_model``: the closed loop of `tt.dit.closed_loop` with the DiffIK policy
  (30 steps) and with the shipped checkpoint's DiT (8 steps), 2 ViperX designs x 2 motions;
* ``mjwarp_viperx``, ``mjwarp_quadruped``, ``newton_viperx``: the other backends on short
  motions (30 / 10 / 30 steps; the quadruped runs tt's whole-body kernels).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _episode_arrays(ep) -> dict[str, np.ndarray]:
    out = {}
    for name in (
        "qpos",
        "qvel",
        "ctrl",
        "action",
        "act_force",
        "act_vel",
        "ee_pos",
        "ee_quat",
        "target_pos",
        "target_quat",
        "alive",
        "fallen",
        "design_index",
        "motion_index",
    ):
        out[name] = getattr(ep, name).detach().cpu().numpy()
    return out


def _short(motions, steps: int):
    from tt.sim.motions.base import Motion

    return [Motion(m.name, m.pos[:steps], m.quat[:steps], m.dt) for m in motions]


def _cases():
    """name -> callable returning {array name: array}."""
    import warp as wp

    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, get_motion
    from tt.sim.rollout import rollout

    viperx = get_space("viperx")
    designs = [viperx.nominal(), *viperx.sample(7, seed=0)]
    motions = for_space([get_motion("toss"), get_motion("scrub")], "viperx")

    def warp_viperx():
        return _episode_arrays(rollout(designs, motions, backend="warp", device="cpu"))

    def warp_viperx_noise():
        return _episode_arrays(rollout(designs, motions, backend="warp", device="cpu", action_noise=0.05, noise_seed=3))

    def warp_twoarm():
        out = {}
        two = for_space([get_motion("bi_fling"), get_motion("bi_fling:1")], "aloha")
        aloha = get_space("aloha")
        ep = rollout([aloha.nominal(), *aloha.sample(1, seed=2)], two, backend="warp", device="cpu")
        out.update({f"aloha/{k}": v for k, v in _episode_arrays(ep).items()})
        bim = for_space([get_motion("bi_fling"), get_motion("bi_fling:1")], "bimanual")
        ep = rollout([get_space("bimanual").nominal()], bim, backend="warp", device="cpu")
        out.update({f"bimanual/{k}": v for k, v in _episode_arrays(ep).items()})
        return out

    def open_loop():
        from tt.kernels import build_tree_model, forward_kinematics, simulate, topology_key

        out = {}
        models = [viperx.model(d) for d in designs]
        sites = viperx.ee_sites()
        groups: dict = {}
        for i, m in enumerate(models):
            groups.setdefault(topology_key(m, sites), []).append(i)
        rng = np.random.default_rng(0)
        for g, members in enumerate(groups.values()):
            ms = [models[i] for i in members]
            tree = build_tree_model(ms, sites, device="cpu")
            nv, nu = ms[0].nv, ms[0].nu
            q0 = np.stack([m.qpos0 for m in ms]).astype(np.float32) + 0.1 * rng.standard_normal((len(ms), nv)).astype(
                np.float32
            )
            ctrl = (0.3 * rng.standard_normal((len(ms), 200, nu))).astype(np.float32)
            res = simulate(
                tree, wp.array(q0, dtype=float), wp.zeros(q0.shape, dtype=float), wp.array(ctrl, dtype=float)
            )
            for k in ("qpos", "qvel", "act_force", "limit_count"):
                out[f"{g}/sim_{k}"] = getattr(res, k).numpy()
            fk = forward_kinematics(tree, wp.array(q0, dtype=float))
            for k in ("xpos", "xquat", "site_pos", "site_quat", "site_jac"):
                out[f"{g}/fk_{k}"] = getattr(fk, k).numpy()
        return out

    def simgrad_case():
        try:
            from tt.sim.rewards import get_reward
        except ImportError:
            from tt.guidance.rewards import get_reward
        from tt.guidance.simgrad import design_reward_gradient

        cfg = get_reward("tracking", "viperx")
        res = design_reward_gradient(
            viperx, [viperx.nominal()], _short(motions[:1], 12), cfg, guidance=False, device="cpu"
        )
        return {"reward": np.asarray(res.reward), "grad": np.asarray(res.grad[0])}

    def dit_ik():
        try:
            from tt.dit.closed_loop import closed_loop_rollout
            from tt.dit.policies import IKPolicy
        except ImportError:  # before the split of tt.dit.controller
            from tt.dit.controller import IKPolicy, closed_loop_rollout

        return _episode_arrays(closed_loop_rollout(designs[:2], motions, IKPolicy(), device="cpu", steps=30))

    def dit_model():
        import torch

        try:
            from tt.dit.policies import model_rollout
        except ImportError:  # before the split of tt.dit.controller
            from tt.dit.controller import model_rollout

        torch.manual_seed(0)
        ep = model_rollout(designs[:2], motions, ROOT / "checkpoints" / "viperx_mini.pt", device="cpu", steps=8)
        return _episode_arrays(ep)

    def mjwarp_viperx():
        return _episode_arrays(rollout(designs[:2], _short(motions[:1], 30), backend="mjwarp", device="cpu"))

    def mjwarp_quadruped():
        quad = get_space("quadruped")
        qm = for_space([get_motion("toss")], "quadruped")
        return _episode_arrays(rollout([quad.nominal()], _short(qm, 10), backend="mjwarp", device="cpu"))

    def newton_viperx():
        return _episode_arrays(rollout(designs[:2], _short(motions[:1], 30), backend="newton", device="cpu"))

    return {
        "warp_viperx": warp_viperx,
        "warp_viperx_noise": warp_viperx_noise,
        "warp_twoarm": warp_twoarm,
        "open_loop": open_loop,
        "simgrad": simgrad_case,
        "dit_ik": dit_ik,
        "dit_model": dit_model,
        "mjwarp_viperx": mjwarp_viperx,
        "mjwarp_quadruped": mjwarp_quadruped,
        "newton_viperx": newton_viperx,
    }


def record(out: Path, only: list[str] | None) -> None:
    import warp as wp

    wp.config.quiet = True
    out.mkdir(parents=True, exist_ok=True)
    for name, fn in _cases().items():
        if only and name not in only:
            continue
        arrays = fn()
        np.savez(out / f"{name}.npz", **arrays)
        print(f"recorded {name}: {len(arrays)} arrays", flush=True)


def compare(before: Path, after: Path) -> int:
    bad = 0
    for f in sorted(before.glob("*.npz")):
        g = after / f.name
        if not g.exists():
            print(f"MISSING {f.stem}")
            bad += 1
            continue
        a, b = np.load(f), np.load(g)
        if set(a.files) != set(b.files):
            print(f"DIFFER {f.stem}: array names {sorted(set(a.files) ^ set(b.files))}")
            bad += 1
            continue
        diff = [
            k
            for k in a.files
            if a[k].shape != b[k].shape or not np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f")
        ]
        if diff:
            k = diff[0]
            d = np.abs(a[k].astype(np.float64) - b[k].astype(np.float64)).max() if a[k].shape == b[k].shape else "shape"
            print(f"DIFFER {f.stem}: {len(diff)} of {len(a.files)} arrays, first {k} (max |diff| {d})")
            bad += 1
        else:
            print(f"IDENTICAL {f.stem}: {len(a.files)} arrays, {sum(a[k].size for k in a.files)} values")
    return 1 if bad else 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("out", type=Path)
    r.add_argument("--only", nargs="*")
    c = sub.add_parser("compare")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    args = p.parse_args(argv)
    if args.cmd == "record":
        record(args.out, args.only)
        return 0
    return compare(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
