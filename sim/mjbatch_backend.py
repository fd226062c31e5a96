"""The ``mjbatch`` rollout backend: MuJoCo C's own physics on a thread pool, tt's batched
whole-body controller; floating-base legged robots (the quadruped), any mix of structures.

Physics is MuJoCo C's ``mj_step`` in float64, exactly what the oracle (`tt.sim.validate`)
runs, stepped by MuJoCo's batch module (``mujoco.batch.Batch``, in the mujoco wheel since
3.17): each simulation is one row of integration state (``mjSTATE_INTEGRATION``: qpos,
qvel, ctrl, the solver's warm start, ...); a call loads the rows into an ``MjData``, steps
them in C++ with the GIL released, saves them back and copies the bound derived fields
(site frames, actuator forces and velocities) into (n, ...) arrays. Its results are
bit-identical to a loop over one ``MjData`` per simulation. One ``Batch`` holds models whose
``MjData`` layout is the same (`layout_key`: every size of the model), each simulation on
its own design's model (``Batch.set_models``), so designs of different structures share a
batch when their sizes agree: 1,024 random quadruped designs (128 structures) fall into 10
layouts.

The controller is the oracle's whole-body IK (`tt.sim.wbc`) as tt's float64 Warp kernels
(`tt.kernels.wbc.wbc_step`: any mix of designs in one launch, the oracle's step to about
1e-13), or with ``controller="mink"`` the oracle's mink controller itself, world by world
on the host (the reference: its episodes equal the oracle's bit for bit).

Threads. The W = D * M worlds (design-major) are cut into ``threads`` contiguous shards;
each shard runs its whole episode on its own Python thread, with its own batches (one per
layout, stepping on the calling thread) and its own controller arrays. MuJoCo's step and
Warp's CPU launches release the GIL, so the shards run in parallel; only the few numpy
copies per layout and control step hold it. Shards never wait for each other, and every
world runs the same calls on the same inputs whichever shard it lands in, so the Episode
is the same bit for bit for every thread count.

Per control step ``k`` of a world (the oracle's loop, `tt.sim.validate`):

1. measured state: the batch's qpos row (at k = 0 the ``home`` keyframe with qpos set to
   the start posture: ``init_iterations`` whole-body IK steps from ``home`` toward the first
   pose, `tt.kernels.wbc.wbc_initial_q`; qvel 0);
2. ``q_cmd`` = the whole-body step toward the motion pose ``min(k + lookahead_steps, T - 1)``
   (float64 targets, as the oracle's);
3. ``ctrl = q_cmd[qpos address of each actuator's joint]``, clipped to ctrlrange where
   limited; with control perturbation (``action_noise`` sigma > 0) the actuators execute
   clip(ctrl + sigma n, ctrlrange), n the standard normals of the Warp rollout kernel
   (`tt.kernels.rollout.action_noise_draws`: a function of (noise_seed, world, step,
   actuator) only, world = its index in the whole call), and ``Episode.action`` records the
   clean ctrl (the "warp" backend's perturbation, in float64);
4. ``substeps`` ``mj_step`` calls, then the forward of the state they reach, so the recorded
   site poses and actuator forces belong to the recorded state: up to the velocity stage
   (``Batch.step(nstep=substeps, stage=mjSTAGE_VEL)``) where every actuator is an affine
   servo (the quadruped's), whose forces `actuator_forces` computes from the actuator
   lengths and velocities as ``mj_fwdActuation`` does, bit for bit; otherwise the whole
   forward (``mjSTAGE_ACC``). The next step recomputes every stage, so the physics is the
   same either way; the velocity stage spares the acceleration stage and its constraint
   solve, about 4 % of a control step's physics (0.94-1.02x over 8 designs,
   benchmarks/results/quadruped_solver.md);
5. records, the termination test (summed end-effector position error over
   ``termination_pos_error``, or a fall, `tt.sim.wbc.fallen`) and the oracle's padding: a
   world stops at its first failing step or at its motion's last one (it is no longer
   stepped) and its later steps repeat that record with alive False.

Speed (benchmarks/results/quadruped_batched.md): one quadruped ``mj_step`` costs about
20-35 us on this CPU, so the physics alone caps a core at roughly 35-45 k world-steps/s
(a world-step: one 0.002 s physics step of one world, the 50 Hz controller included).
"""

from __future__ import annotations

import functools
import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Sequence

import mujoco
import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.sim.backends.base import Robots, check_motions
from tt.sim.controller import IKConfig, actuated_qpos, model_name
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion
from tt.sim.wbc import HOME_KEY, WBCConfig, WholeBodyController, fallen, foot_site_names, free_joint, standing_height

logger = logging.getLogger(__name__)

#: Controllers: tt's batched whole-body kernels, or the oracle's mink controller on the host.
CONTROLLERS = ("kernel", "mink")

#: Episode fields recorded per step from the physics, and which model size pads each.
_JOINT_FIELDS = {"qpos": "nq", "qvel": "nv", "ctrl": "nu", "act_force": "nu", "act_vel": "nu"}
#: Fields a terminated world repeats from its last step (and ``action`` when perturbed).
_REPEATED = ("qpos", "qvel", "ctrl", "act_force", "act_vel", "ee_pos", "ee_quat", "fallen")


@functools.cache
def _size_fields() -> tuple[str, ...]:
    """Names of MjModel's integer size attributes (``nq``, ``nbody``, ``narena``, ...)."""
    probe = mujoco.MjModel.from_xml_string("<mujoco/>")
    return tuple(n for n in dir(probe) if n.startswith("n") and isinstance(getattr(probe, n), int))


def layout_key(model: mujoco.MjModel) -> tuple[int, ...]:
    """Every integer size of `model` (nq, nv, nu, nbody, ngeom, nsite, neq, narena, ...):
    models with equal keys give ``MjData`` one layout, so one ``mujoco.batch.Batch`` runs
    them (each on its own model). A superset of what the layout needs (names' lengths,
    keyframe counts), which can only split a batch, never join incompatible models."""
    return tuple(int(getattr(model, n)) for n in _size_fields())


def mat2quat(mat: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of rotation matrices (..., 9) (row-major, MuJoCo's ``xmat``), MuJoCo's
    ``mju_mat2Quat`` branch for branch (so the sign is the one the oracle records), in
    float64; shape (..., 4)."""
    m = np.asarray(mat, dtype=np.float64)
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = np.moveaxis(m, -1, 0)
    tr = m0 + m4 + m8
    q = np.zeros(m.shape[:-1] + (4,))
    with np.errstate(invalid="ignore", divide="ignore"):
        b0 = tr > 0
        b1 = ~b0 & (m0 > m4) & (m0 > m8)
        b2 = ~b0 & ~b1 & (m4 > m8)
        b3 = ~b0 & ~b1 & ~b2
        w = 0.5 * np.sqrt(1.0 + tr)
        x = 0.5 * np.sqrt(1.0 + m0 - m4 - m8)
        y = 0.5 * np.sqrt(1.0 - m0 + m4 - m8)
        z = 0.5 * np.sqrt(1.0 - m0 - m4 + m8)
        cases = (
            (b0, (w, 0.25 * (m7 - m5) / w, 0.25 * (m2 - m6) / w, 0.25 * (m3 - m1) / w)),
            (b1, (0.25 * (m7 - m5) / x, x, 0.25 * (m1 + m3) / x, 0.25 * (m2 + m6) / x)),
            (b2, (0.25 * (m2 - m6) / y, 0.25 * (m1 + m3) / y, y, 0.25 * (m5 + m7) / y)),
            (b3, (0.25 * (m3 - m1) / z, 0.25 * (m2 + m6) / z, 0.25 * (m5 + m7) / z, z)),
        )
        for mask, parts in cases:
            for i, part in enumerate(parts):
                q[..., i] = np.where(mask, part, q[..., i])
        norm = np.sqrt(np.sum(q * q, axis=-1, keepdims=True))
    # mju_normalize4: the identity for a (near) zero quaternion; no division within
    # mjMINVAL of unit length.
    small = norm < mujoco.mjMINVAL
    scale = np.where(small | (np.abs(norm - 1.0) <= mujoco.mjMINVAL), 1.0, norm)
    return np.where(small, np.array([1.0, 0.0, 0.0, 0.0]), q / scale)


@dataclass
class _Records:
    """The Episode's arrays of W worlds x T steps (float32, bool), filled shard by shard."""

    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray
    act_force: np.ndarray
    act_vel: np.ndarray
    ee_pos: np.ndarray
    ee_quat: np.ndarray
    alive: np.ndarray
    fallen: np.ndarray
    action: np.ndarray | None = None  # the clean commands, under control perturbation only

    @classmethod
    def zeros(cls, W: int, T: int, nq: int, nv: int, nu: int, A: int, perturbed: bool = False) -> "_Records":
        def f(*shape):
            return np.zeros(shape, np.float32)

        return cls(
            qpos=f(W, T, nq), qvel=f(W, T, nv), ctrl=f(W, T, nu), act_force=f(W, T, nu), act_vel=f(W, T, nu),
            ee_pos=f(W, T, A, 3), ee_quat=f(W, T, A, 4),
            alive=np.zeros((W, T), bool), fallen=np.zeros((W, T), bool),
            action=f(W, T, nu) if perturbed else None,
        )  # fmt: skip


@dataclass
class _Layout:
    """The simulations of one shard that share an MjData layout: one batch."""

    batch: object  # mujoco.batch.Batch
    local: np.ndarray  # shard-local world indices, in simulation order
    nq: int
    nv: int
    nu: int
    bound: dict = field(default_factory=dict)
    #: (gain, bias0, bias1, bias2, force_lo, force_hi), each (nsim, nu), where every actuator of
    #: the layout's models is MuJoCo's affine servo (`affine_actuators`); None steps to stage ACC.
    force: tuple | None = None


@dataclass
class _Shard:
    """Worlds [lo, hi) and everything one thread needs to run them."""

    lo: int
    hi: int
    models: list  # per world
    motion: np.ndarray  # (Ws,) motion index per world
    layouts: list = field(default_factory=list)


def mjbatch_rollout(
    robots: Robots,
    motions: Sequence[Motion],
    *,
    config: IKConfig = WBCConfig(),
    threads: int | None = None,
    progress: bool = False,
    controller: str = "kernel",
    action_noise: float = 0.0,
    noise_seed: int = 0,
) -> Episode:
    """Run every robot on every motion with MuJoCo C physics; an Episode of W = D * M
    worlds (design-major: world ``d * M + m`` is design d on motion m), CPU tensors.

    robots: floating-base legged robots (`tt.sim.backends.base.resolve_designs`): a free
        joint on the first body, foot sites ``foot_*``, a ``home`` keyframe (the quadruped).
    motions: M motions sampled at the controller's control_dt, one arm per end effector.
    config: the whole-body controller's settings (a `WBCConfig`; a plain `IKConfig`, the
        rollout's default, means `WBCConfig()`).
    threads: CPU threads the worlds are spread over (None: every core this process may use);
        the Episode is the same bit for bit for every count.
    progress: a tqdm bar over control steps (of every shard).
    controller: "kernel" (tt's batched whole-body kernels) or "mink" (the oracle's
        controller on the host, world by world: the reference, as slow as the oracle's).
    action_noise: control perturbation, the standard deviation [rad or m] of the Gaussian
        noise on every executed command (``Episode.ctrl``; ``Episode.action`` holds the clean
        one); 0: none. noise_seed: its seed, 0..2**31-1; the draws are the "warp" backend's
        (`tt.kernels.rollout.action_noise_draws`) for the same seed and world.
    Returns the oracle's Episode (`tt.sim.validate.oracle_rollout`): joint fields zero-padded
    to the widest design, records repeated with alive False after a world stopped.
    """
    from mujoco.batch import Batch  # noqa: F401  (fails early where the wheel lacks it)

    from tt.kernels.rollout import _check_noise, cpu_threads, world_slices

    _check_noise(action_noise, noise_seed)
    if controller not in CONTROLLERS:
        raise TTError(f"controller = {controller!r}; expected one of {CONTROLLERS}")
    wbc_config = config if isinstance(config, WBCConfig) else WBCConfig()
    models, sites = list(robots.models), robots.ee_sites
    for i, m in enumerate(models):
        if free_joint(m) is None:
            raise TTError(
                f"designs[{i}] ({model_name(m)!r}) has no free joint; the 'mjbatch' backend runs floating-base "
                "legged robots (the quadruped): use backend 'warp' (or 'mujoco') for fixed-base arms"
            )
        foot_site_names(m)  # a floating base without feet raises here
        actuated_qpos(m)  # every actuator must drive a hinge or slide joint
        wbc_config.substeps(m)
    check_motions(motions, wbc_config.control_dt, len(sites))
    D, M, A = len(models), len(motions), len(sites)
    W, T = D * M, max(motion.steps for motion in motions)
    mpos = np.zeros((M, T, A, 3))
    mquat = np.zeros((M, T, A, 4))
    msteps = np.array([motion.steps for motion in motions])
    for j, motion in enumerate(motions):
        idx = np.minimum(np.arange(T), motion.steps - 1)
        mpos[j], mquat[j] = motion.pos[idx], motion.quat[idx]
    sizes = {k: max(getattr(m, k) for m in models) for k in ("nq", "nv", "nu")}
    perturbed = action_noise > 0.0
    rec = _Records.zeros(W, T, sizes["nq"], sizes["nv"], sizes["nu"], A, perturbed)

    world_model = [models[w // M] for w in range(W)]
    world_motion = np.arange(W) % M
    shards = [
        _Shard(lo, hi, world_model[lo:hi], world_motion[lo:hi]) for lo, hi in world_slices(W, cpu_threads(threads))
    ]
    logger.debug("mjbatch rollout: %d worlds (%d designs x %d motions), T=%d, %d shard(s)", W, D, M, T, len(shards))
    if controller == "kernel" or perturbed:
        import warp as wp

        wp.init()
    if controller == "kernel":
        from tt.kernels.wbc import load_wbc_kernels

        load_wbc_kernels("cpu")  # once, before the threads launch them
    if perturbed:
        from tt.kernels.rollout import _noise_draws

        wp.load_module(_noise_draws.module, device="cpu")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T * len(shards), desc="mjbatch", unit="step")
    lock = threading.Lock()
    run = functools.partial(
        _run_shard, rec=rec, sites=sites, mpos=mpos, mquat=mquat, msteps=msteps, steps=T, config=wbc_config,
        controller=controller, bar=bar, lock=lock, action_noise=float(action_noise), noise_seed=int(noise_seed),
    )  # fmt: skip
    try:
        if len(shards) == 1:
            run(shards[0])
        else:
            with ThreadPoolExecutor(len(shards), thread_name_prefix="tt-mjbatch") as pool:
                for future in [pool.submit(run, shard) for shard in shards]:
                    future.result()
    finally:
        if bar is not None:
            bar.close()

    tensors = {name: torch.from_numpy(getattr(rec, name)) for name in (*_JOINT_FIELDS, "ee_pos", "ee_quat")}
    world_index = np.minimum(np.arange(T), msteps[world_motion][:, None] - 1)  # (W, T)
    return Episode(
        **tensors,
        action=torch.from_numpy(rec.action) if perturbed else tensors["ctrl"].clone(),
        target_pos=torch.from_numpy(mpos[world_motion[:, None], world_index].astype(np.float32)),
        target_quat=torch.from_numpy(mquat[world_motion[:, None], world_index].astype(np.float32)),
        alive=torch.from_numpy(rec.alive),
        fallen=torch.from_numpy(rec.fallen),
        design_index=torch.arange(D).repeat_interleave(M),
        motion_index=torch.arange(M).repeat(D),
        dt=wbc_config.control_dt,
    )


def _build_layouts(shard: _Shard) -> None:
    """One batch per MjData layout of the shard's worlds, each world on its own model, reset
    to the ``home`` keyframe (qpos and ctrl) with its kinematics computed, derived fields bound."""
    from mujoco.batch import Batch

    groups: dict[tuple, list[int]] = {}
    for i, m in enumerate(shard.models):
        groups.setdefault(layout_key(m), []).append(i)
    for local in groups.values():
        ms = [shard.models[i] for i in local]
        batch = Batch(ms[0], nsim=len(ms), nthread=1)  # runs on the shard's own thread
        batch.set_models(ms)
        # Outputs are bound before the first call, so every call copies them out.
        force = affine_actuators(ms)
        # The actuator forces come from the step's acceleration stage, or, for affine servos,
        # from their length and velocity (stage VEL), which spares the constraint solve.
        forces = ("actuator_length",) if force is not None else ("actuator_force",)
        bound = {
            name: batch.bind(name)
            for name in ("qpos", "qvel", "ctrl", *forces, "actuator_velocity", "site_xpos", "site_xmat")
        }
        # The home pose's kinematics: its foot sites are the stance points.
        keys = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, HOME_KEY) for m in ms])
        batch.reset(keyframe=keys, stage=mujoco.mjtStage.mjSTAGE_POS.value)
        shard.layouts.append(_Layout(batch, np.array(local), ms[0].nq, ms[0].nv, ms[0].nu, bound, force))


def affine_actuators(models: Sequence[mujoco.MjModel]) -> tuple | None:
    """(gain, bias0, bias1, bias2, force_lo, force_hi), each (len(models), nu), of models whose
    actuators are all stateless with a fixed gain and an affine or no bias (MuJoCo's position
    and velocity servos, the quadruped's); None if any actuator of any model is another kind
    or a model disables actuation.

    With these, `actuator_forces` gives what MuJoCo's ``mj_fwdActuation`` computes."""
    fixed, affine, none = mujoco.mjtGain.mjGAIN_FIXED, mujoco.mjtBias.mjBIAS_AFFINE, mujoco.mjtBias.mjBIAS_NONE
    for m in models:
        if (
            m.na
            or m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_ACTUATION
            or not (
                np.all(m.actuator_dyntype == mujoco.mjtDyn.mjDYN_NONE)
                and np.all(m.actuator_gaintype == fixed)
                and np.all((m.actuator_biastype == affine) | (m.actuator_biastype == none))
            )
        ):
            return None
    bias = np.stack(
        [np.where((m.actuator_biastype == affine)[:, None], m.actuator_biasprm[:, :3], 0.0) for m in models]
    )
    limited = np.stack([m.actuator_forcelimited.astype(bool) for m in models])
    frange = np.stack([m.actuator_forcerange for m in models])
    return (
        np.stack([m.actuator_gainprm[:, 0] for m in models]), bias[..., 0], bias[..., 1], bias[..., 2],
        np.where(limited, frange[..., 0], -np.inf), np.where(limited, frange[..., 1], np.inf),
    )  # fmt: skip


def actuator_forces(force: tuple, ctrl: np.ndarray, length: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """Actuator forces (n, nu) of `affine_actuators`' servos at controls `ctrl` (within their
    ctrlrange), actuator lengths and velocities (n, nu): ``mj_fwdActuation``'s arithmetic in
    its order (gain * ctrl, then + (b0 + b1 * length + b2 * velocity), then the force range)."""
    gain, b0, b1, b2, lo, hi = force
    return np.clip(gain * ctrl + (b0 + b1 * length + b2 * velocity), lo, hi)


def _run_shard(
    shard: _Shard,
    *,
    rec: _Records,
    sites: tuple[str, ...],
    mpos: np.ndarray,
    mquat: np.ndarray,
    msteps: np.ndarray,
    steps: int,
    config: WBCConfig,
    controller: str,
    bar,
    lock: threading.Lock,
    action_noise: float = 0.0,
    noise_seed: int = 0,
) -> None:
    """The whole episode of one shard's worlds, written into rows [lo, hi) of `rec`."""
    from mujoco.batch import SimulationError

    Ws, A = shard.hi - shard.lo, len(sites)
    models = shard.models
    NQ, NU = max(m.nq for m in models), max(m.nu for m in models)
    substeps = config.substeps(models[0])
    lookahead = config.lookahead_steps
    threshold = config.termination_pos_error
    acc, vel = mujoco.mjtStage.mjSTAGE_ACC.value, mujoco.mjtStage.mjSTAGE_VEL.value
    rows = np.arange(shard.lo, shard.hi)
    wsteps = msteps[shard.motion]

    # Per world: actuator -> qpos address, ctrl clip, end-effector sites, base, fall height.
    act_qpos = np.zeros((Ws, NU), np.int64)
    lo = np.full((Ws, NU), -np.inf)
    hi = np.full((Ws, NU), np.inf)
    site_ids = np.zeros((Ws, A), np.int64)
    base = np.zeros(Ws, np.int64)
    height = np.zeros(Ws)
    feet: list[list[int]] = []
    per_model: dict[int, tuple] = {}
    for i, m in enumerate(models):
        if id(m) not in per_model:
            limited = m.actuator_ctrllimited.astype(bool)
            rng = np.where(limited[:, None], m.actuator_ctrlrange, [-np.inf, np.inf])
            ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s) for s in sites]
            foot_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s) for s in foot_site_names(m)]
            per_model[id(m)] = (
                actuated_qpos(m), rng, ids, int(m.jnt_qposadr[free_joint(m)]), standing_height(m), foot_ids,
            )  # fmt: skip
        aq, rng, ids, b, h, foot_ids = per_model[id(m)]
        act_qpos[i, : m.nu], lo[i, : m.nu], hi[i, : m.nu] = aq, rng[:, 0], rng[:, 1]
        site_ids[i], base[i], height[i] = ids, b, h
        feet.append(foot_ids)

    _build_layouts(shard)
    # Stance points (the foot sites in the home pose) from the batches' kinematics, in C.
    stance: list = [None] * Ws
    for lay in shard.layouts:
        xpos = lay.bound["site_xpos"]
        for sim, i in enumerate(lay.local):
            stance[i] = xpos[sim, feet[i]]
    q = np.zeros((Ws, NQ))
    first_pos, first_quat = mpos[shard.motion, 0], mquat[shard.motion, 0]
    if controller == "kernel":
        import warp as wp

        from tt.kernels.wbc import make_wbc_data, wbc_initial_q, wbc_step
        from tt.sim.wbc_model import build_wbc_model

        wbc = build_wbc_model(models, config, device="cpu", stance=stance)
        wbc_data = make_wbc_data(wbc, Ws, device="cpu")
        q_w = wp.zeros((Ws, wbc.nq), dtype=wp.float64, device="cpu")
        q_cmd_w = wp.zeros((Ws, wbc.nq), dtype=wp.float64, device="cpu")
        tpos_w = wp.array(first_pos, dtype=wp.vec3d, device="cpu")
        tquat_w = wp.array(first_quat, dtype=wp.vec4d, device="cpu")
        q0 = wbc_initial_q(wbc, tpos_w, tquat_w, config.init_iterations, data=wbc_data, device="cpu").numpy()
        # Zero-copy numpy views of the kernel's inputs and output.
        q, q_cmd, tpos, tquat = q_w.numpy(), q_cmd_w.numpy(), tpos_w.numpy(), tquat_w.numpy()
    else:
        controllers = {id(m): WholeBodyController(m, config) for m in models}  # this thread's own
        q0 = np.zeros((Ws, NQ))
        for i, m in enumerate(models):
            q0[i, : m.nq] = controllers[id(m)].initial_q(first_pos[i], first_quat[i])
        q_cmd = np.zeros((Ws, NQ))
        tpos, tquat = first_pos.copy(), first_quat.copy()
    for lay in shard.layouts:
        lay.bound["qpos"][:] = q0[lay.local, : lay.nq]
        lay.bound["qvel"][:] = 0.0

    noise = None
    if action_noise > 0.0:
        from tt.kernels.rollout import action_noise_draws

        # The Warp rollout's standard normals of these worlds, keyed by their index in the call.
        noise = action_noise_draws(noise_seed, rows, steps, NU).astype(np.float64)  # (Ws, T, NU)
    done = 0
    live = np.ones(Ws, bool)
    last = np.full(Ws, steps - 1)
    for t in range(steps):
        if not live.any():
            break
        for lay in shard.layouts:
            q[lay.local, : lay.nq] = lay.bound["qpos"]
        goal = np.minimum(t + lookahead, wsteps - 1)
        tpos[:] = mpos[shard.motion, goal]
        tquat[:] = mquat[shard.motion, goal]
        if controller == "kernel":
            wbc_step(wbc, q_w, tpos_w, tquat_w, q_cmd_w, data=wbc_data, device="cpu")
        else:
            for i in np.flatnonzero(live):
                m = models[i]
                q_cmd[i, : m.nq] = controllers[id(m)].step(q[i, : m.nq], tpos[i], tquat[i])
        ctrl = np.clip(np.take_along_axis(q_cmd, act_qpos, axis=1), lo, hi)
        executed = ctrl if noise is None else np.clip(ctrl + action_noise * noise[:, t], lo, hi)
        target = mpos[shard.motion, np.minimum(t, wsteps - 1)]  # (Ws, A, 3): the current target
        for lay in shard.layouts:
            sim_live = live[lay.local]
            if not sim_live.any():
                continue
            local = lay.local[sim_live]
            b = lay.bound
            b["ctrl"][sim_live] = executed[local, : lay.nu]
            try:
                lay.batch.step(ids=sim_live, nstep=substeps, stage=acc if lay.force is None else vel)
            except SimulationError as exc:  # MuJoCo raised (mju_error) in some simulations
                worlds = [int(rows[lay.local[i]]) for i in exc.ids[:5]]
                raise TTError(f"MuJoCo raised at control step {t} in worlds {worlds}: {exc}") from exc
            r = rows[local]
            qpos = b["qpos"][sim_live]
            rec.qpos[r, t, : lay.nq] = qpos
            rec.qvel[r, t, : lay.nv] = b["qvel"][sim_live]
            rec.ctrl[r, t, : lay.nu] = executed[local, : lay.nu]
            if rec.action is not None:
                rec.action[r, t, : lay.nu] = ctrl[local, : lay.nu]
            if lay.force is None:
                rec.act_force[r, t, : lay.nu] = b["actuator_force"][sim_live]
            else:
                force = tuple(p[sim_live] for p in lay.force)
                rec.act_force[r, t, : lay.nu] = actuator_forces(
                    force, executed[local, : lay.nu], b["actuator_length"][sim_live], b["actuator_velocity"][sim_live]
                )
            rec.act_vel[r, t, : lay.nu] = b["actuator_velocity"][sim_live]
            n = np.arange(len(local))[:, None]
            ee_pos = b["site_xpos"][sim_live][n, site_ids[local]]  # (n, A, 3)
            ee_mat = b["site_xmat"][sim_live][n, site_ids[local]]  # (n, A, 9)
            rec.ee_pos[r, t] = ee_pos
            rec.ee_quat[r, t] = mat2quat(ee_mat)
            error = np.linalg.norm(ee_pos - target[local], axis=-1).sum(axis=-1)
            bq = base[local][:, None] + np.arange(7)
            state = np.take_along_axis(qpos, bq, axis=1)
            fell = fallen(state[:, :3], state[:, 3:], height[local], config)
            rec.fallen[r, t] = fell
            with np.errstate(invalid="ignore"):
                bad = ~np.isfinite(error) | (error > threshold) | fell
            rec.alive[r, t] = ~bad
            stop = bad | (t == wsteps[local] - 1)
            live[local[stop]] = False
            last[local[stop]] = t
        done += 1
        if bar is not None:
            with lock:
                bar.update(1)
    if bar is not None and done < steps:
        with lock:
            bar.update(steps - done)

    # A stopped world repeats its last record (alive stays False).
    for i in np.flatnonzero(last < steps - 1):
        w, k = rows[i], last[i]
        for name in _REPEATED + (("action",) if rec.action is not None else ()):
            arr = getattr(rec, name)
            arr[w, k + 1 :] = arr[w, k]


__all__ = ["CONTROLLERS", "actuator_forces", "affine_actuators", "layout_key", "mat2quat", "mjbatch_rollout"]
