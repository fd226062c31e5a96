"""The fused rollout: controller and physics of one world in one thread, many steps a launch.

Per world and control step t (the oracle's loop, `tt.sim.validate`, step for step):

1. state (q, qd) at the start of the step; at t = 0 the oracle's start posture, at rest:
   ``init_iterations`` kinematic IK steps from qpos0 toward the motion's first pose;
2. IK target: the motion pose at min(t + lookahead, T_m - 1); q_cmd = DiffIK step
   (`tt.kernels.ik`); action = clip(q_cmd of each actuated joint, ctrlrange); the command
   executed is ctrl = action, or with control perturbation (``action_noise`` sigma > 0)
   ctrl = clip(action + sigma n, ctrlrange), n ~ N(0, 1) per actuator (`action_noise_draws`);
3. `substeps` physics steps (`tt.kernels.dynamics`) with ctrl held;
4. record q, qd, ctrl, action (with perturbation only), actuator forces and velocities at the
   new state, end-effector poses (`tt.kernels.fk`) and the target at index min(t, T_m - 1);
5. termination: the step is alive while the position error summed over end effectors
   stays within `threshold`; the first step past it keeps its record with alive False,
   and every later step (also every step after the motion's last) repeats the last record
   with alive False.

Perturbation noise is a function of (seed, world id, t, actuator) only: Warp's PCG hash
(`wp.rand_init`) keyed by the world id and then by the control step, two uniforms per
actuator turned Gaussian by Box-Muller. So it does not depend on the chunking, the thread
schedule or the device (the integer stream is identical everywhere; log and cos are float32
library calls, equal to within an ulp or two between CPU and CUDA), and sigma = 0 skips it
entirely, leaving the noise-free kernel's arithmetic untouched.

All of a world's working memory is thread-local; the only memory it writes is its records
(one time slice per step, never overwritten) and its physics state buffer. The state
buffer has L slots, slot (s mod L) holding the state after physics step s: with L = 1 the
state is updated in place (forward only, minimal memory); with L = T * substeps + 1 every
physics step writes a fresh slot, so the kernel's adjoint (Warp replays each dynamic loop
iteration from memory) is exact and gradients of any function of the records with respect
to the model's continuous fields (link offsets `body_pos`, mount pose, masses, gains) can
be taken with `wp.Tape`.

Kernels are compiled once per `Topology` (`rollout_kernels`), the differentiable rollout in
a separate module that is built only when first asked for (`grad_kernels`), and the start
posture alone in a third (`start_postures`, for the backends that run other physics).

The launch wrappers take numbers, not configs: the IK's `IKWeights` struct and the
controller's timing and termination as plain arguments; `tt.sim.controller.IKConfig`
turns its settings into them (`IKConfig.ik_weights`, `IKConfig.rollout_args`).

On the CPU Warp runs a launch on the calling thread, one world after another. Since worlds
are independent, `rollout_tree` cuts them into a few contiguous slices per thread and
launches each from a pool of `threads` Python threads on array views of that slice
(`_world_views`, which also cuts the arrays inside the model's struct): a CPU launch is a
call through a ``ctypes.CFUNCTYPE`` pointer, which releases the GIL for the kernel's whole
run, and the generated CPU kernel keeps its task index in a parameter (no static state),
so launches on disjoint slices run in parallel. Every world runs the same code on the same
inputs whichever slice it lands in, so the records are bit-identical for any thread count.
"""

import functools
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from types import SimpleNamespace
from typing import TYPE_CHECKING, Sequence

import numpy as np
import warp as wp

from tt.kernels.dynamics import dynamics_funcs
from tt.kernels.errors import TTError
from tt.kernels.fk import kinematics_funcs
from tt.kernels.ik import IKWeights, ik_funcs
from tt.kernels.lie import wxyz
from tt.kernels.model import (
    DIFFERENTIABLE_MODULE_OPTIONS,
    MODULE_OPTIONS,
    Kinematics64,
    Topology,
    TreeArrays,
    TreeModel,
    local_types,
    module_name,
    topology_constants,
)
from tt.kernels.pose import position_error

if TYPE_CHECKING:
    import mujoco


@wp.func
def _noise_state(seed: int, world: int, t: int):
    """PCG state of world `world`'s control step `t` (a per-world key, then the step)."""
    return wp.rand_init(wp.int32(wp.rand_init(seed, world)), t)


@wp.func
def _standard_normal(u1: float, u2: float):
    """Box-Muller: a standard normal from two uniforms in [0, 1) (1 - u1 > 0: log stays finite)."""
    return wp.sqrt(-2.0 * wp.log(1.0 - u1)) * wp.cos(2.0 * wp.pi * u2)


def make_rollout_kernel(topology: Topology, module: str, differentiable: bool = False):
    """The fused rollout kernel of one topology, registered in Warp module `module`
    (`differentiable`: with the physics variant whose adjoint is exact, see `dynamics_funcs`)."""
    T = local_types(topology)
    K = kinematics_funcs(topology)
    Dyn = dynamics_funcs(topology, differentiable)
    IK = ik_funcs(topology)
    NV, NU, NE = topology.dof_count, topology.actuator_count, topology.ee_count
    ACT_DOF = topology_constants(topology).actuator_dof

    @wp.kernel(module=module)
    def _rollout(
        # Model:
        model: TreeArrays,
        # In:
        weights: IKWeights,
        lookahead: int,
        substeps: int,
        threshold: float,
        t_begin: int,
        t_end: int,
        motion_pos_in: wp.array3d(dtype=wp.vec3),
        motion_quat_in: wp.array3d(dtype=wp.vec4),
        motion_steps_in: wp.array(dtype=wp.int32),
        noise_std: float,
        noise_seed: int,
        noise_world_in: wp.array(dtype=wp.int32),
        # Data in / out (physics state, slot s mod L after physics step s):
        qpos_state: wp.array3d(dtype=float),
        qvel_state: wp.array3d(dtype=float),
        # Data out (records, (W, T, ...)):
        qpos_out: wp.array3d(dtype=float),
        qvel_out: wp.array3d(dtype=float),
        ctrl_out: wp.array3d(dtype=float),
        act_force_out: wp.array3d(dtype=float),
        act_vel_out: wp.array3d(dtype=float),
        ee_pos_out: wp.array3d(dtype=wp.vec3),
        ee_quat_out: wp.array3d(dtype=wp.vec4),
        target_pos_out: wp.array3d(dtype=wp.vec3),
        target_quat_out: wp.array3d(dtype=wp.vec4),
        alive_out: wp.array2d(dtype=wp.bool),
        action_out: wp.array3d(dtype=float),  # written only when noise_std > 0
    ):
        worldid = wp.tid()
        mid = worldid % model.body_pos.shape[0]
        motionid = worldid % motion_pos_in.shape[0]
        motion_steps = motion_steps_in[motionid]
        slots = qpos_state.shape[1]
        for t in range(t_begin, t_end):
            record = wp.min(t, motion_steps - 1)
            for e in range(NE):
                target_pos_out[worldid, t, e] = motion_pos_in[motionid, record, e]
                target_quat_out[worldid, t, e] = motion_quat_in[motionid, record, e]
            stopped = t >= motion_steps
            if t > 0:
                if not alive_out[worldid, t - 1]:
                    stopped = True
            if stopped:
                # Past termination or the motion's end: repeat the last record.
                for d in range(NV):
                    qpos_out[worldid, t, d] = qpos_out[worldid, t - 1, d]
                    qvel_out[worldid, t, d] = qvel_out[worldid, t - 1, d]
                for u in range(NU):
                    ctrl_out[worldid, t, u] = ctrl_out[worldid, t - 1, u]
                    act_force_out[worldid, t, u] = act_force_out[worldid, t - 1, u]
                    act_vel_out[worldid, t, u] = act_vel_out[worldid, t - 1, u]
                if noise_std > 0.0:
                    for u in range(NU):
                        action_out[worldid, t, u] = action_out[worldid, t - 1, u]
                for e in range(NE):
                    ee_pos_out[worldid, t, e] = ee_pos_out[worldid, t - 1, e]
                    ee_quat_out[worldid, t, e] = ee_quat_out[worldid, t - 1, e]
                alive_out[worldid, t] = False
            else:
                # Controller, at the state of the start of the step.
                s0 = t * substeps
                q = T.dof_vec()
                for d in range(NV):
                    q[d] = qpos_state[worldid, s0 % slots, d]
                goal = wp.min(t + lookahead, motion_steps - 1)
                tpos = T.ee_vec3()
                tquat = T.ee_vec4()
                for e in range(NE):
                    tpos[e] = motion_pos_in[motionid, goal, e]
                    tquat[e] = motion_quat_in[motionid, goal, e]
                xpos, xquat, axis, anchor = K.kinematics(mid, model, q)
                q_cmd = IK.command(mid, model, xpos, xquat, axis, anchor, q, tpos, tquat, weights)
                ctrl = T.act_vec()
                for u in range(NU):
                    cr = model.act_ctrlrange[mid, u]
                    ctrl[u] = wp.clamp(q_cmd[ACT_DOF[u]], cr[0], cr[1])
                if noise_std > 0.0:
                    # Control perturbation: log the clean command, execute a noisy one.
                    rng = _noise_state(noise_seed, noise_world_in[worldid], t)
                    for u in range(NU):
                        action_out[worldid, t, u] = ctrl[u]
                        u1 = wp.randf(rng)
                        u2 = wp.randf(rng)
                        cr = model.act_ctrlrange[mid, u]
                        ctrl[u] = wp.clamp(ctrl[u] + noise_std * _standard_normal(u1, u2), cr[0], cr[1])

                # Physics, with the command held.
                for k in range(substeps):
                    s = s0 + k
                    qk = T.dof_vec()
                    qdk = T.dof_vec()
                    for d in range(NV):
                        qk[d] = qpos_state[worldid, s % slots, d]
                        qdk[d] = qvel_state[worldid, s % slots, d]
                    qn, qdn, force, vel, active = Dyn.step(mid, model, qk, qdk, ctrl)
                    for d in range(NV):
                        qpos_state[worldid, (s + 1) % slots, d] = qn[d]
                        qvel_state[worldid, (s + 1) % slots, d] = qdn[d]

                # Record the state after the step, with what belongs to it.
                s1 = s0 + substeps
                q1 = T.dof_vec()
                qd1 = T.dof_vec()
                for d in range(NV):
                    q1[d] = qpos_state[worldid, s1 % slots, d]
                    qd1[d] = qvel_state[worldid, s1 % slots, d]
                    qpos_out[worldid, t, d] = q1[d]
                    qvel_out[worldid, t, d] = qd1[d]
                qfrc, force1, vel1 = Dyn.actuation(mid, model, q1, qd1, ctrl)
                for u in range(NU):
                    ctrl_out[worldid, t, u] = ctrl[u]
                    act_force_out[worldid, t, u] = force1[u]
                    act_vel_out[worldid, t, u] = vel1[u]
                xpos1, xquat1, axis1, anchor1 = K.kinematics(mid, model, q1)
                error = float(0.0)
                for e in range(NE):
                    p, r = K.site_pose(e, xpos1, xquat1, model, mid)
                    ee_pos_out[worldid, t, e] = p
                    ee_quat_out[worldid, t, e] = wxyz(r)
                    error += position_error(p, motion_pos_in[motionid, record, e])
                # `<=` so that a NaN error (a diverged state) terminates like a large one.
                alive_out[worldid, t] = error <= threshold

    return _rollout


def make_initial_posture_kernel(topology: Topology, module: str):
    """The start-posture kernel of one topology (``iterations`` kinematic IK steps from
    qpos0 toward the motion's first pose), registered in module `module`.

    It computes in float64 from float64 model fields and first poses: fifty IK steps toward
    a pose the robot may not reach can wander chaotically (differences of 1e-7 rad grow to
    radians), so float32 or float32-rounded inputs would end in a different posture from the
    oracle's for a few percent of random designs.
    """
    S = wp.float64
    T = local_types(topology, S)
    K = kinematics_funcs(topology, S)
    IK = ik_funcs(topology, S)
    NV, NE = topology.dof_count, topology.ee_count

    @wp.kernel(module=module)
    def _initial_posture(
        # Model (float64 kinematic fields):
        model: Kinematics64,
        # In:
        weights: IKWeights,
        iterations: int,
        motion_pos_in: wp.array2d(dtype=T.vec3),
        motion_quat_in: wp.array2d(dtype=T.vec4),
        # Data out (iterate i in slot i mod L, then the start state in slot 0):
        q_iter: wp.array3d(dtype=wp.float64),
        qpos_state_out: wp.array3d(dtype=float),
    ):
        worldid = wp.tid()
        mid = worldid % model.body_pos.shape[0]
        motionid = worldid % motion_pos_in.shape[0]
        slots = q_iter.shape[1]
        tpos = T.ee_vec3()
        tquat = T.ee_vec4()
        for e in range(NE):
            tpos[e] = motion_pos_in[motionid, e]
            tquat[e] = motion_quat_in[motionid, e]
        for d in range(NV):
            q_iter[worldid, 0, d] = model.dof_ref[mid, d]
        for i in range(iterations):
            q = T.dof_vec()
            for d in range(NV):
                q[d] = q_iter[worldid, i % slots, d]
            xpos, xquat, axis, anchor = K.kinematics(mid, model, q)
            q_cmd = IK.command(mid, model, xpos, xquat, axis, anchor, q, tpos, tquat, weights)
            for d in range(NV):
                q_iter[worldid, (i + 1) % slots, d] = q_cmd[d]
        for d in range(NV):
            qpos_state_out[worldid, 0, d] = float(q_iter[worldid, iterations % slots, d])

    return _initial_posture


@functools.cache
def rollout_kernels(topology: Topology) -> SimpleNamespace:
    """The forward-only rollout kernels of a topology (start posture and rollout, one module)."""
    module = module_name(topology, "rollout")
    wp.set_module_options(MODULE_OPTIONS, module)
    return SimpleNamespace(
        module=module,
        initial_posture=make_initial_posture_kernel(topology, module),
        rollout=make_rollout_kernel(topology, module),
    )


@functools.cache
def grad_kernels(topology: Topology) -> SimpleNamespace:
    """The differentiable rollout of a topology (its own module, with adjoints).

    Load it with `load_differentiable` before the first launch: the kernels overwrite
    components of thread-local vectors and matrices, whose adjoints Warp gets right only
    when the module is built with ``enable_vector_component_overwrites``.
    """
    module = module_name(topology, "rollout_grad")
    wp.set_module_options(DIFFERENTIABLE_MODULE_OPTIONS, module)
    return SimpleNamespace(
        module=module,
        initial_posture=make_initial_posture_kernel(topology, module),
        rollout=make_rollout_kernel(topology, module, differentiable=True),
    )


def preload_rollout_kernels(models: Sequence["mujoco.MjModel"], ee_sites: Sequence[str], device: str) -> None:
    """Hash and build (or load from the kernel cache) the forward rollout module of each
    distinct topology of `models` on `device`, as the first `rollout_tree` launch would.

    A module missing from the kernel cache takes seconds to build (9-12 s per fused
    rollout module of a 6-15-dof robot on one core of a 2-core CPU,
    benchmarks/results/compile_cost.md; a cached one loads in milliseconds, its hash needs no
    code generation, see `tt.kernels.generated`), so a caller with idle time, e.g. while
    worker processes compile models, can take the build off the rollout's critical path.
    Loading twice is a no-op.
    """
    from tt.kernels.model import topology_key, topology_of

    seen = set()
    for model in models:
        key = topology_key(model, ee_sites)
        if key not in seen:
            seen.add(key)
            wp.load_module(rollout_kernels(topology_of(model, ee_sites)).module, device=device)


def module_built(module: str, device: str) -> bool:
    """Whether Warp module `module` loads on `device` without a compile: it is loaded there
    already, or its binary and metadata are in Warp's kernel cache (``wp.config.kernel_cache_dir``).

    Costs the module's hash, which its first load computes anyway and keeps (no code
    generation for tt's modules, see `tt.kernels.generated`), and two file checks. The cache
    paths are Warp's own (``Module.load``'s): the variant a plain launch loads (block_dim 1 on
    the CPU, the module's default on CUDA). Where this Warp names its files otherwise, the
    module counts as built: the answer only decides whether to show a compile's progress.
    """
    wp.init()
    dev = wp.get_device(device)
    m = wp.get_module(module)
    block_dim = 1 if dev.is_cpu else m.options["block_dim"]
    if (dev.context, block_dim) in m.execs:
        return True
    try:
        folder = os.path.join(wp.config.kernel_cache_dir, m.get_module_identifier(block_dim))
        binary = m._get_compile_output_name(dev, block_dim=block_dim)
        meta = m._get_meta_name(block_dim=block_dim)
    except (AttributeError, TypeError):  # another Warp's private API
        return True
    return os.path.exists(os.path.join(folder, binary)) and os.path.exists(os.path.join(folder, meta))


def load_differentiable(topology: Topology, device: str) -> SimpleNamespace:
    """`grad_kernels(topology)`, built and loaded on `device`.

    Warp reads ``enable_vector_component_overwrites`` from its global config when it first
    hashes a module (and keeps that hash), so the flag is set only around that point and
    restored, leaving every other module as the user configured it.
    """
    kernels = grad_kernels(topology)
    previous = wp.config.enable_vector_component_overwrites
    wp.config.enable_vector_component_overwrites = True
    try:
        wp.load_module(kernels.module, device=device)
    finally:
        wp.config.enable_vector_component_overwrites = previous
    return kernels


@functools.cache
def start_posture_kernel(topology: Topology):
    """The float64 start-posture kernel of a topology (`make_initial_posture_kernel`) in a
    module of its own, so that callers that only need the start posture (the mjwarp and
    newton backends, the model controller's loop) do not compile the fused rollout."""
    module = module_name(topology, "start_posture")
    wp.set_module_options(MODULE_OPTIONS, module)
    return make_initial_posture_kernel(topology, module)


def start_postures(
    model: TreeModel, motions: "MotionArrays", weights: IKWeights, iterations: int, *, device: str | None = None
) -> wp.array:
    """Start postures (W, NV) float32 of the worlds of `model` (world i runs model entry i
    and motion i % M): `iterations` float64 IK steps from qpos0 toward each world's first
    motion pose (``motions.first_pos``, ``first_quat``), as
    `tt.sim.controller.DiffIKController.initial_q` does (weights: `IKConfig.init_ik_weights`)."""
    device = device or model.device
    W, NV = model.world_count, model.topology.dof_count
    q_iter = wp.zeros((W, 1, NV), dtype=wp.float64, device=device)
    out = wp.zeros((W, 1, NV), dtype=float, device=device)
    wp.launch(
        start_posture_kernel(model.topology),
        dim=W,
        inputs=[model.kinematics64, weights, int(iterations), motions.first_pos, motions.first_quat],
        outputs=[q_iter, out],
        device=device,
    )
    return out.reshape((W, NV))


@wp.kernel(enable_backward=False)
def _noise_draws(seed: int, world_in: wp.array(dtype=wp.int32), t_begin: int, draws_out: wp.array3d(dtype=float)):
    w, i = wp.tid()
    rng = _noise_state(seed, world_in[w], t_begin + i)
    for u in range(draws_out.shape[2]):
        u1 = wp.randf(rng)
        u2 = wp.randf(rng)
        draws_out[w, i, u] = _standard_normal(u1, u2)


def action_noise_draws(
    noise_seed: int, world_ids, steps: int, actuator_count: int, *, t_begin: int = 0, device: str = "cpu"
) -> np.ndarray:
    """The standard normals n the rollout kernel draws for control perturbation, (W, steps, NU)
    float32: world ``world_ids[i]``'s control steps t_begin, ..., t_begin + steps - 1. World w
    of a rollout with ``action_noise`` sigma executes clip(action + sigma n[w, t], ctrlrange)."""
    _check_noise(0.0, noise_seed)
    ids = wp.array(np.asarray(world_ids, dtype=np.int32), dtype=wp.int32, device=device)
    out = wp.zeros((ids.shape[0], steps, actuator_count), dtype=float, device=device)
    wp.launch(
        _noise_draws,
        dim=(ids.shape[0], steps),
        inputs=[int(noise_seed), ids, int(t_begin)],
        outputs=[out],
        device=device,
    )
    return out.numpy()


def _check_noise(action_noise: float, noise_seed: int) -> None:
    if not (np.isfinite(action_noise) and action_noise >= 0.0):
        raise TTError(f"action_noise = {action_noise!r}; must be a finite standard deviation >= 0 [rad or m]")
    if not isinstance(noise_seed, (int, np.integer)) or not 0 <= noise_seed < 2**31:
        raise TTError(f"noise_seed = {noise_seed!r}; must be an integer in 0..2**31-1")


@dataclass
class RolloutArrays:
    """Records of W worlds over T control steps, as Warp arrays (see `Episode` for meanings).

    qpos, qvel: (W, T, NV) float; ctrl (executed), act_force, act_vel: (W, T, NU) float;
    action: the clean commands, (W, T, NU) float; the same array as ``ctrl`` when the
    rollout has no control perturbation;
    ee_pos, target_pos: (W, T, NE) vec3; ee_quat, target_quat: (W, T, NE) vec4 (w, x, y, z);
    alive: (W, T) bool; qpos_state, qvel_state: (W, L, NV) physics state buffer.
    """

    qpos: wp.array
    qvel: wp.array
    ctrl: wp.array
    action: wp.array
    act_force: wp.array
    act_vel: wp.array
    ee_pos: wp.array
    ee_quat: wp.array
    target_pos: wp.array
    target_quat: wp.array
    alive: wp.array
    qpos_state: wp.array
    qvel_state: wp.array


@dataclass
class MotionArrays:
    """M target motions padded to a common length T, on the device.

    pos: (M, T, NE) vec3 [m]; quat: (M, T, NE) vec4 (w, x, y, z); steps: (M,) int32, each
    motion's own length; first_pos, first_quat: the first poses in float64, (M, NE) (the
    start posture is solved toward them in float64).
    """

    pos: wp.array
    quat: wp.array
    steps: wp.array
    first_pos: wp.array
    first_quat: wp.array

    @property
    def count(self) -> int:
        return self.pos.shape[0]


def motion_arrays(
    pos: np.ndarray, quat: np.ndarray, steps, *, device: str, requires_grad: bool = False
) -> MotionArrays:
    """`MotionArrays` from padded host arrays pos (M, T, NE, 3), quat (M, T, NE, 4) and the
    motions' lengths `steps` (M,)."""
    pos = np.asarray(pos, dtype=np.float64)
    quat = np.asarray(quat, dtype=np.float64)
    return MotionArrays(
        pos=wp.array(pos.astype(np.float32), dtype=wp.vec3, device=device, requires_grad=requires_grad),
        quat=wp.array(quat.astype(np.float32), dtype=wp.vec4, device=device, requires_grad=requires_grad),
        steps=wp.array(np.asarray(steps, dtype=np.int32), dtype=wp.int32, device=device),
        first_pos=wp.array(np.ascontiguousarray(pos[:, 0]), dtype=wp.vec3d, device=device),
        first_quat=wp.array(np.ascontiguousarray(quat[:, 0]), dtype=wp.types.vector(4, wp.float64), device=device),
    )


#: Slices of worlds per CPU thread in a threaded launch (load balance; see `rollout_tree`).
#: 16 measured no better than 4 (`benchmarks/ab_slices.py`, results/ab_slices.md: within the
#: spread of repeated runs on a 2-core box).
SLICES_PER_THREAD = 4
#: Fewest worlds in a slice: a launch costs ~0.1 ms of Python, a 50-step chunk of 16 worlds
#: ~10 ms of stepping, so the threads' overhead stays near 1 % (fewer worlds: one launch).
MIN_SLICE_WORLDS = 16


def cpu_threads(threads: int | None = None) -> int:
    """Threads for a CPU rollout: `threads`, or every core this process may run on (None).

    Raises ValueError for a count < 1.
    """
    if threads is None:
        try:
            return len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            return os.cpu_count() or 1
    if not isinstance(threads, (int, np.integer)) or isinstance(threads, bool) or threads < 1:
        raise TTError(f"threads = {threads!r}; must be an integer >= 1 (None: every core)")
    return int(threads)


def world_slices(world_count: int, count: int, align: int = 1) -> list[tuple[int, int]]:
    """Split worlds 0..world_count-1 into at most `count` contiguous [lo, hi) slices of
    near-equal size whose starts are multiples of `align` (so per-motion or per-model
    indexing ``world % align`` is unchanged inside a slice)."""
    blocks = -(-world_count // align)
    count = max(1, min(count, blocks))
    cuts = [min(world_count, (blocks * k // count) * align) for k in range(count + 1)]
    return [(lo, hi) for lo, hi in zip(cuts[:-1], cuts[1:]) if hi > lo]


def _world_views(obj, lo: int, hi: int, worlds: int):
    """`obj` (a Warp array, a `wp.struct` instance, or a list of them) with every array whose
    leading dimension is `worlds` cut to the view [lo:hi]; other arrays (broadcast entries,
    shared inputs) and values are kept whole."""
    if isinstance(obj, wp.array):
        return obj[lo:hi] if obj.ndim >= 1 and obj.shape[0] == worlds else obj
    if isinstance(obj, (list, tuple)):
        return type(obj)(_world_views(x, lo, hi, worlds) for x in obj)
    struct = getattr(obj, "_cls", None)
    if struct is not None and hasattr(struct, "vars"):  # a wp.struct instance
        values = {name: getattr(obj, name) for name in struct.vars}
        views = {name: _world_views(v, lo, hi, worlds) for name, v in values.items()}
        if all(views[name] is values[name] for name in values):
            return obj
        view = type(obj)()
        for name, v in views.items():
            setattr(view, name, v)
        return view
    return obj


class _SlicedLaunch:
    """Launches of one kernel over `dim` worlds, one per [lo, hi) of `slices` on views of the
    per-world arrays, from the threads of `pool` (one slice: one launch on this thread, and
    no pool needed).

    The views are cut once, here: a rollout launches the same arrays once per chunk, and
    cutting them again each time cost ~0.5 s of Python per 4,096-world episode, on a core
    the stepping threads need.
    """

    def __init__(
        self, kernel, *, dim: int, inputs: list, outputs: list, device, slices, pool: ThreadPoolExecutor | None = None
    ):
        if len(slices) > 1 and pool is None:
            raise ValueError(f"{len(slices)} slices of worlds need a thread pool to launch them from")
        self.kernel, self.dim, self.device, self.pool = kernel, dim, device, pool
        if len(slices) == 1:
            self.views = [(dim, list(inputs), list(outputs))]
        else:
            self.views = [
                (hi - lo, list(_world_views(inputs, lo, hi, dim)), list(_world_views(outputs, lo, hi, dim)))
                for lo, hi in slices
            ]  # fmt: skip

    def __call__(self, scalars: dict[int, object] | None = None) -> None:
        """Launch every slice; `scalars` replaces inputs by position (values, not arrays)."""

        def launch(worlds: int, inputs: list, outputs: list) -> None:
            if scalars:
                inputs = list(inputs)
                for i, value in scalars.items():
                    inputs[i] = value
            wp.launch(self.kernel, dim=worlds, inputs=inputs, outputs=outputs, device=self.device)

        if len(self.views) == 1:
            launch(*self.views[0])
            return
        for f in [self.pool.submit(launch, *view) for view in self.views]:
            f.result()


def rollout_tree(
    model: TreeModel,
    motions: MotionArrays,
    world_count: int,
    steps: int,
    *,
    weights: IKWeights,
    control_dt: float,
    lookahead_steps: int,
    termination_pos_error: float,
    init_iterations: int,
    init_weights: IKWeights,
    differentiable: bool = False,
    initial_qpos: np.ndarray | None = None,
    chunk: int | None = None,
    progress=None,
    action_noise: float = 0.0,
    noise_seed: int = 0,
    world_ids: np.ndarray | None = None,
    device: str | None = None,
    threads: int | None = None,
    graph: bool | None = None,
    pool: ThreadPoolExecutor | None = None,
) -> RolloutArrays:
    """Closed-loop rollouts of `world_count` worlds of one topology for `steps` control steps.

    World w runs model entry w % model.world_count on motion w % M (M = motions.count; with
    one model entry per world and worlds design-major, world d * M + m is design d on
    motion m). `motions` comes from `motion_arrays`.
    weights, control_dt [s], lookahead_steps, termination_pos_error [m], init_iterations:
        the controller (`IKWeights`; control period, a whole number of every model's
        timesteps; IK target index t + lookahead_steps; summed end-effector position
        error past which a world terminates; start-posture IK steps), as
        `tt.sim.controller.IKConfig.rollout_args` gives them.
    init_weights: the start posture's weights (`IKConfig.init_ik_weights`: a larger
        damping than the loop's `weights`).
    differentiable: use the kernel with adjoints and a state slot per physics step, so the
        call can be recorded on a `wp.Tape` (memory grows with W * steps * substeps).
        Gradients flow through the controller and the physics to the float32 model fields;
        the start posture (a float64 IK iteration, see `make_initial_posture_kernel`) reads
        `model.kinematics64`, so its gradient reaches those float64 copies (when they
        require grad), not the float32 fields; for robots that cannot reach the first pose
        that iteration is chaotic and its derivative not informative (pass `initial_qpos`
        to hold the start fixed).
    initial_qpos: start postures (W, NV) [rad or m] to use instead of the start-posture kernel.
    chunk: control steps per launch (None: all in one); progress: a callable taking the
        number of control steps done after each launch (e.g. a tqdm bar's update).
    action_noise: control perturbation, the standard deviation sigma [rad or m, the
        actuator's unit] of Gaussian noise added to every executed command: ctrl =
        clip(action + sigma n, ctrlrange) while ``action`` records the clean command
        (0: none; ``action`` is then ``ctrl``). The noise is the same for every chunking and
        device (see `action_noise_draws`); no gradient flows through it.
    noise_seed: seed of the noise, 0..2**31-1. world_ids: (W,) ints keying each world's
        noise (default 0..W-1); a caller splitting one batch into launches passes the
        worlds' indices in the whole batch, so the noise does not depend on the split.
    threads: CPU threads the worlds are spread over (None: every core, `cpu_threads`);
        the records are the same bit for bit for every count. CUDA launches and the
        differentiable rollout (one `wp.Tape` records every launch) use one launch.
    graph: launch the start posture and every chunk as one captured graph (`wp.ScopedCapture`,
        replayed by `wp.capture_launch`): one driver submission instead of one per launch.
        None (default): on a CUDA device yes, on the CPU plain launches (Warp 1.19 can
        replay a CPU capture too, which the tests use to check both paths agree; a capture
        records one thread's launches, so it runs on one thread); False: plain launches
        everywhere. `progress` is then called once, after the replay. Not with
        ``differentiable`` (a `wp.Tape` records the plain launches).
    pool: a thread pool of `threads` workers to launch the slices from, shared with other
        rollouts running at the same time (the caller shuts it down and must have loaded
        the topology's module, `rollout_kernels`, beforehand); None: one of this rollout's own.
    """
    topo = model.topology
    device = device or model.device
    dt = model.timestep_host
    ratio = control_dt / dt
    substeps = np.rint(ratio).astype(int)
    if np.any(substeps < 1) or np.any(np.abs(ratio - substeps) > 1e-6 * ratio) or len(set(substeps.tolist())) != 1:
        raise TTError(
            f"model timesteps {sorted(set(dt.tolist()))} s must all divide control_dt "
            f"{control_dt} s into one whole number of physics steps"
        )
    substeps = int(substeps[0])
    _check_noise(action_noise, noise_seed)
    W, NV, NU, NE = world_count, topo.dof_count, max(topo.actuator_count, 1), topo.ee_count
    world_ids = np.arange(W) if world_ids is None else np.asarray(world_ids)
    if world_ids.shape != (W,):
        raise TTError(f"world_ids has shape {world_ids.shape}; expected ({W},), one id per world")
    if motions.pos.ndim != 3 or motions.pos.shape[2] != NE:
        raise TTError(f"motion pos has shape {motions.pos.shape}; expected (M, T, {NE}) for {NE} end effector(s)")
    if steps < 1:
        raise TTError(f"steps = {steps}; a rollout needs at least one control step")
    slots = steps * substeps + 1 if differentiable else 1

    def zeros(shape, dtype, grad=differentiable):
        return wp.zeros(shape, dtype=dtype, device=device, requires_grad=grad)

    ctrl = zeros((W, steps, NU), float)
    out = RolloutArrays(
        qpos=zeros((W, steps, NV), float),
        qvel=zeros((W, steps, NV), float),
        ctrl=ctrl,
        # Without perturbation the kernel never writes `action_out`: ctrl stands in for it.
        action=zeros((W, steps, NU), float) if action_noise > 0.0 else ctrl,
        act_force=zeros((W, steps, NU), float),
        act_vel=zeros((W, steps, NU), float),
        ee_pos=zeros((W, steps, NE), wp.vec3),
        ee_quat=zeros((W, steps, NE), wp.vec4),
        target_pos=zeros((W, steps, NE), wp.vec3),
        target_quat=zeros((W, steps, NE), wp.vec4),
        alive=zeros((W, steps), wp.bool, grad=False),
        qpos_state=zeros((W, slots, NV), float),
        qvel_state=zeros((W, slots, NV), float),
    )
    noise_world = wp.array(world_ids.astype(np.int32), dtype=wp.int32, device=device)
    kernels = load_differentiable(topo, device) if differentiable else rollout_kernels(topo)
    use_graph = wp.get_device(device).is_cuda if graph is None else bool(graph)
    if use_graph and differentiable:
        if graph:
            raise TTError(
                "graph=True with differentiable=True: a wp.Tape records plain launches; pass graph=False or None"
            )
        use_graph = False
    threads = cpu_threads(threads)
    if differentiable or use_graph or wp.get_device(device).is_cuda:
        threads = 1
    # Slices start at multiples of every leading dimension read as ``world % n`` that is not
    # W itself (arrays of W entries are cut to the slice), so each world reads what it would
    # read in one launch. A few slices per thread, taken from a queue: worlds that terminate
    # early cost little, so equal slices can take unequal times.
    align = math.lcm(*(n for n in (model.world_count, motions.count) if n != W))
    count = min(threads * SLICES_PER_THREAD, max(1, W // MIN_SLICE_WORLDS)) if threads > 1 else 1
    slices = world_slices(W, count, align)
    # One pool for the whole rollout: the start posture and every chunk's launches.
    own_pool = None
    if len(slices) == 1:
        pool = None
    elif pool is None:
        wp.load_module(kernels.module, device=device)  # once, before the threads launch
        pool = own_pool = ThreadPoolExecutor(min(threads, len(slices)), thread_name_prefix="tt-rollout")
    # Start at rest at the oracle's start posture (IK from qpos0 toward the first pose).
    iterations = int(init_iterations)
    q_iter = zeros((W, iterations + 1 if differentiable else 1, NV), wp.float64)
    if initial_qpos is not None:
        start = np.zeros((W, slots, NV), np.float32)
        start[:, 0] = initial_qpos
        out.qpos_state.assign(start)
    chunk = steps if chunk is None else max(1, int(chunk))
    chunks = [(t0, min(steps, t0 + chunk)) for t0 in range(0, steps, chunk)]

    start_posture = _SlicedLaunch(
        kernels.initial_posture,
        dim=W,
        inputs=[model.kinematics64, init_weights, iterations, motions.first_pos, motions.first_quat],
        outputs=[q_iter, out.qpos_state],
        device=device, slices=slices, pool=pool,
    )  # fmt: skip
    T0, T1 = 5, 6  # positions of the chunk's first and end step among the rollout's inputs
    step_chunk = _SlicedLaunch(
        kernels.rollout,
        dim=W,
        inputs=[
            model.arrays,
            weights,
            int(lookahead_steps),
            substeps,
            float(termination_pos_error),
            0,
            0,
            motions.pos,
            motions.quat,
            motions.steps,
            float(action_noise),
            int(noise_seed),
            noise_world,
            out.qpos_state,
            out.qvel_state,
        ],  # fmt: skip
        outputs=[
            out.qpos,
            out.qvel,
            out.ctrl,
            out.act_force,
            out.act_vel,
            out.ee_pos,
            out.ee_quat,
            out.target_pos,
            out.target_quat,
            out.alive,
            out.action,
        ],  # fmt: skip
        device=device,
        slices=slices,
        pool=pool,
    )

    def launch(t0: int, t1: int) -> None:
        step_chunk({T0: t0, T1: t1})

    if use_graph:
        # Load (compile) outside the capture: drivers before CUDA 12.3 cannot load modules
        # while a stream is being captured.
        wp.load_module(kernels.module, device=device)
        with wp.ScopedCapture(device=device) as capture:
            if initial_qpos is None:
                start_posture()
            for t0, t1 in chunks:
                launch(t0, t1)
        wp.capture_launch(capture.graph)
        if progress is not None:
            progress(steps)
        return out
    try:
        if initial_qpos is None:
            start_posture()
        for t0, t1 in chunks:
            launch(t0, t1)
            if progress is not None:
                progress(t1 - t0)
    finally:
        if own_pool is not None:
            own_pool.shutdown()
    return out
