"""Per-core cost of tt's fused rollout kernel, against its parts and against FK alone.

One CPU thread, one ViperX topology (the most common among the random designs), W worlds
of that topology, in one process. Four kernels run on the same `TreeModel`:

* fused: `tt.kernels.rollout.rollout_tree` on the toss (controller at 50 Hz: FK + DLS IK;
  10 physics steps per control step; records, FK of the new state, termination);
* physics: `dynamics_funcs(...).step` alone, 10 per control step, commands held at the start
  posture (FK, composite inertias, mass matrix, RNEA, LTDL factor + solve, joint limits);
* controller: FK + `ik_funcs(...).command` alone, once per control step (the IK iterated
  kinematically, as the start posture does);
* FK: `kinematics_funcs(...).kinematics` alone, once per physics step: the reference cost.

Costs are CPU ns per world-step (this process's CPU time on its one thread, best of
``--repeats`` interleaved rounds; one physics step of one world; the controller's cost is
spread over its 10 physics steps) and in FK units (the cost of one FK in the same
harness). ``fused - physics - controller`` is what the records and the per-step
bookkeeping cost. Every kernel loops inside the world's thread for the whole episode
(no launch per step) and writes a checksum, so the compiler cannot drop the work.

Writes ``--out`` (default benchmarks/results/kernel_cost.md). Usage:
    python benchmarks/kernel_cost.py [--worlds 1024] [--repeats 5]
"""

# No `from __future__ import annotations`: Warp reads the kernels' annotations as objects.
import argparse
import os
import time
from collections import Counter
from pathlib import Path

import numpy as np

try:
    from machine import machine_header
except ImportError:  # run as a module from the repository root
    from benchmarks.machine import machine_header

SUBSTEPS = 10


def _kernels(topology):
    """The three part kernels of one topology, in their own Warp module."""
    import warp as wp

    from tt.kernels.dynamics import dynamics_funcs
    from tt.kernels.fk import kinematics_funcs
    from tt.kernels.ik import IKWeights, ik_funcs
    from tt.kernels.model import MODULE_OPTIONS, TreeArrays, local_types, module_name, topology_constants

    module = module_name(topology, "cost")
    wp.set_module_options(MODULE_OPTIONS, module)
    T = local_types(topology)
    K = kinematics_funcs(topology)
    Dyn = dynamics_funcs(topology)
    IK = ik_funcs(topology)
    NV, NB, NE, NU = topology.dof_count, topology.body_count, topology.ee_count, topology.actuator_count
    ACT_DOF = topology_constants(topology).actuator_dof

    @wp.kernel(module=module)
    def fk_only(model: TreeArrays, q0: wp.array2d(dtype=float), iterations: int, out: wp.array(dtype=float)):
        w = wp.tid()
        q = T.dof_vec()
        for d in range(NV):
            q[d] = q0[w, d]
        acc = float(0.0)
        for i in range(iterations):
            xpos, xquat, axis, anchor = K.kinematics(w, model, q)
            acc += xpos[NB - 1][0] + xquat[NB - 1][1] + axis[NV - 1][2] + anchor[NV - 1][0]
            for d in range(NV):
                q[d] = q[d] + 1.0e-4  # a new posture each time: no FK result can be reused
        out[w] = acc

    @wp.kernel(module=module)
    def physics_only(model: TreeArrays, q0: wp.array2d(dtype=float), iterations: int, out: wp.array(dtype=float)):
        w = wp.tid()
        q = T.dof_vec()
        qd = T.dof_vec()
        for d in range(NV):
            q[d] = q0[w, d]
        ctrl = T.act_vec()
        for u in range(NU):
            ctrl[u] = q0[w, ACT_DOF[u]]
        for i in range(iterations):
            q, qd, force, vel, active = Dyn.step(w, model, q, qd, ctrl)
        acc = float(0.0)
        for d in range(NV):
            acc += q[d] + qd[d]
        out[w] = acc

    @wp.kernel(module=module)
    def controller_only(
        model: TreeArrays,
        weights: IKWeights,
        q0: wp.array2d(dtype=float),
        motion_pos: wp.array2d(dtype=wp.vec3),
        motion_quat: wp.array2d(dtype=wp.vec4),
        iterations: int,
        out: wp.array(dtype=float),
    ):
        w = wp.tid()
        q = T.dof_vec()
        for d in range(NV):
            q[d] = q0[w, d]
        for i in range(iterations):
            tpos = T.ee_vec3()
            tquat = T.ee_vec4()
            for e in range(NE):
                tpos[e] = motion_pos[i % motion_pos.shape[0], e]
                tquat[e] = motion_quat[i % motion_pos.shape[0], e]
            xpos, xquat, axis, anchor = K.kinematics(w, model, q)
            q = IK.command(w, model, xpos, xquat, axis, anchor, q, tpos, tquat, weights)
        acc = float(0.0)
        for d in range(NV):
            acc += q[d]
        out[w] = acc

    return module, fk_only, physics_only, controller_only


def common_topology_models(space, worlds: int) -> list:
    """MuJoCo models of up to `worlds` random designs of `space` (a `DesignSpace`) that share
    the most common topology among 4 x `worlds` draws (seed 0)."""
    from tt.kernels.model import topology_key

    sites = space.ee_sites()
    pool = space.models(space.sample(4 * worlds, seed=0))
    keys = [topology_key(m, sites) for m in pool]
    key, _ = Counter(keys).most_common(1)[0]
    return [m for m, k in zip(pool, keys) if k == key][:worlds]


def _best(fn, repeats: int) -> float:
    """The least CPU time of this process over `repeats` calls of `fn`: every kernel runs on
    this one thread, so CPU time is the per-core cost, and other jobs on the machine (which
    stretch wall time) change it little."""
    times = []
    for _ in range(repeats):
        start = time.process_time()
        fn()
        times.append(time.process_time() - start)
    return min(times)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=None, help="control steps (default: the whole toss)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "kernel_cost.md")
    args = ap.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    from tt.kernels.model import build_tree_model, topology_of
    from tt.kernels.rollout import motion_arrays, rollout_tree
    from tt.sim.controller import IKConfig
    from tt.sim.designs import get_space
    from tt.sim.motions import for_space, get_motion

    load_before = os.getloadavg()
    space = get_space("viperx")
    sites = space.ee_sites()
    models = common_topology_models(space, args.worlds)
    W = len(models)
    topo = topology_of(models[0], sites)
    tree = build_tree_model(models, sites, device="cpu")
    toss = for_space([get_motion("toss")], "viperx")[0]
    steps = min(args.steps or toss.steps, toss.steps)
    marrays = motion_arrays(toss.pos[None, :steps], toss.quat[None, :steps], [steps], device="cpu")
    config = IKConfig()

    # The start postures of the fused rollout, so every part starts where the rollout does.
    rollout_args = config.rollout_args()
    start = rollout_tree(tree, marrays, W, 1, **rollout_args, threads=1, device="cpu")
    q0 = wp.array(start.qpos_state.numpy()[:, 0], dtype=float, device="cpu")
    module, fk_only, physics_only, controller_only = _kernels(topo)
    t0 = time.perf_counter()
    wp.load_module(module, device="cpu")
    compile_s = time.perf_counter() - t0
    out = wp.zeros(W, dtype=float, device="cpu")
    physics_steps = steps * SUBSTEPS

    def fused():
        return rollout_tree(
            tree, marrays, W, steps, **rollout_args, threads=1, chunk=None, initial_qpos=q0.numpy(), device="cpu"
        )

    def fk():
        wp.launch(fk_only, dim=W, inputs=[tree.arrays, q0, physics_steps, out], device="cpu")

    def physics():
        wp.launch(physics_only, dim=W, inputs=[tree.arrays, q0, physics_steps, out], device="cpu")

    mpos = wp.array(toss.pos[:steps].astype(np.float32), dtype=wp.vec3, device="cpu")
    mquat = wp.array(toss.quat[:steps].astype(np.float32), dtype=wp.vec4, device="cpu")

    def controller():
        wp.launch(controller_only, dim=W, inputs=[tree.arrays, config.ik_weights(), q0, mpos, mquat, steps, out],
                  device="cpu")  # fmt: skip

    for f in (fused, fk, physics, controller):  # warm: first-call costs out of the timings
        f()
    # A world past termination only repeats its record: the fused kernel's cost is per
    # executed world-step (the alive steps and the one that terminated a world).
    alive = fused().alive.numpy().sum(axis=1)
    executed = int((alive + (alive < steps)).sum()) * SUBSTEPS
    # Interleaved rounds, best of each: the parts are compared under the same load.
    best = {name: float("inf") for name in ("fused", "physics", "controller", "fk")}
    loads = []
    for _ in range(args.repeats):
        for name, f in (("fused", fused), ("physics", physics), ("controller", controller), ("fk", fk)):
            best[name] = min(best[name], _best(f, 1))
        loads.append(os.getloadavg()[0])
    world_steps = W * physics_steps
    ns = {name: 1e9 * t / world_steps for name, t in best.items()}  # the controller's: spread over 10 physics steps
    ns["fused"] = 1e9 * best["fused"] / executed
    fk_ns = ns["fk"]
    rest = ns["fused"] - ns["physics"] - ns["controller"]
    rows = [
        ("fused rollout (controller + physics + records), per executed world-step", ns["fused"]),
        ("physics step (dynamics + integration), 500 Hz", ns["physics"]),
        ("controller (FK + DLS IK), 50 Hz, per physics step", ns["controller"]),
        ("records, termination, bookkeeping (fused - physics - controller)", rest),
        ("FK alone, once per physics step (reference)", fk_ns),
    ]
    table = "| part | CPU ns per world-step | FK units | share of fused |\n|---|---:|---:|---:|\n" + "\n".join(
        f"| {name} | {v:.0f} | {v / fk_ns:.1f} | {100 * v / ns['fused']:.0f} % |" for name, v in rows
    )
    la = os.getloadavg()
    text = (
        "# Per-core cost of the fused rollout kernel\n\n"
        + machine_header("cpu")
        + f"- command: `python benchmarks/kernel_cost.py {' '.join(argv if argv is not None else [])}`".rstrip()
        + "\n"
        f"- load average (1, 5, 15 min): {load_before[0]:.1f}, {load_before[1]:.1f}, {load_before[2]:.1f} at "
        "the start, "
        f"{la[0]:.1f}, {la[1]:.1f}, {la[2]:.1f} at the end; 1-min load {min(loads):.1f}-{max(loads):.1f} during the "
        f"{args.repeats} interleaved rounds (best of each kernel kept)\n"
        f"- {W} ViperX designs of one topology ({topo.dof_count} DoF, {topo.body_count - 1} bodies), the toss's first "
        f"{steps} control steps, one CPU thread; the part kernels compiled in {compile_s:.0f} s\n\n" + table + "\n\n"
        f"One executed world-step of the fused kernel costs {ns['fused'] / fk_ns:.1f} FKs of the same robot "
        f"({100 * executed / world_steps:.0f} % of the fused rollout's world-steps were executed). The physics kernel "
        "holds the start posture as its command, so its joint-limit work can differ from the rollout's.\n"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
