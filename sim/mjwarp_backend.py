"""The ``mjwarp`` rollout backend: MuJoCo-Warp physics, W worlds per launch, tt's controllers.

MuJoCo-Warp (``mujoco_warp``, imported as ``mjw``) steps W worlds of one MuJoCo model at
a time. Designs of one *structure* (`structure_key`: the same bodies, joints, geoms,
actuators and options, differing only in numbers) share one `mjw.Model` whose
numeric fields that may vary per world (MuJoCo-Warp marks them with a leading ``*``
dimension in ``mujoco_warp/_src/types.py``: body offsets and inertias, joint axes and
ranges, geom sizes, actuator gains, ...) hold one entry per world (`batch_model`); a
kernel reads entry ``worldid % shape[0]``. Structure groups refine tt's topology groups
(`tt.kernels.model.topology_key`): ViperX designs form 3 of each, one per DoF count.
Unlike the ``warp`` backend this one simulates everything MuJoCo-Warp does, contacts and
equality constraints included, so it runs the quadruped too.

Control, per world and control step (the oracle's loop, `tt.sim.validate`, step for step):

* fixed-base arms: tt's batched DiffIK kernel (`tt.kernels.ik.ik_step`, the oracle's mink
  step, with forward kinematics on MuJoCo-Warp's ``qpos``), one launch per structure
  group; the start posture is the oracle's float64 IK from ``qpos0`` toward the first
  pose (`tt.kernels.rollout.start_postures`). An arm
  whose model has contacts gets its IK from a copy with contacts disabled (the IK reads
  only the kinematic tree); MuJoCo-Warp simulates the contacts;
* floating-base legged robots (the quadruped): tt's batched whole-body kernels
  (`tt.kernels.wbc.wbc_step`, the oracle's `tt.sim.wbc.WholeBodyController` step in
  float64, any mix of designs in one launch per structure group), start posture by the
  same kernels from ``home`` (`tt.kernels.wbc.wbc_initial_q`). A world that terminated
  keeps its last command, as the oracle stops it. ``floating_controller="mink"`` runs the
  oracle's controller itself on the host instead, one world at a time (the reference the
  kernel path is tested against; as slow as the oracle's controller).

Physics runs ``IKConfig.substeps(model)`` MuJoCo-Warp steps per control step with the
command held, then one ``mjw.forward`` so the recorded site poses and actuator
forces belong to the recorded state, as the oracle's ``mj_forward`` does. Worlds that
terminated keep stepping in lockstep with the others but their records repeat the last
one, alive False, which is what the oracle records.

Records are written straight into one Episode-shaped set of Warp arrays (zero-padded to
the widest design across structure groups, `tt.kernels.records`), and the Episode's
tensors are zero-copy torch views of them. This module is host code: every kernel it
launches lives in `tt.kernels` (`records`, `control`, `ik`, `wbc`, `rollout`'s start posture).

`mjwarp_simulate` runs open-loop commands (the dynamics reference of the tests).

Speed: on the CPU device every `mjw.step` is about 80 kernel launches, so small batches
are bound by Python's launch overhead and each structure group adds its own launches;
see ``benchmarks/results/sim.md``.

Gradients: MuJoCo-Warp 3.17 is not differentiable through ``mjw.step`` (a `wp.Tape`
over it returns all-zero gradients); use the ``warp`` backend (tt's kernels) or the
``newton`` backend (Featherstone) for gradients.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import logging
import math
from dataclasses import dataclass
from typing import Sequence

import mujoco
import numpy as np
import torch
import warp as wp

from tt.kernels.errors import TTError
from tt.kernels.records import RecordArrays
from tt.sim.backends import Robots, get_backend
from tt.sim.controller import IKConfig, actuated_qpos, model_name
from tt.sim.designs import Design
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion
from tt.sim.wbc import HOME_KEY, WBCConfig, WholeBodyController, foot_site_names, free_joint, standing_height

logger = logging.getLogger(__name__)

#: MuJoCo's flags of frames that coincide (body and inertia frame, geom and body frame):
#: value-derived shortcuts of MuJoCo C that MuJoCo-Warp 3.17 never reads, so designs may
#: differ in them and still share one `mjw.Model` (random link offsets toggle them).
_IGNORED_INT_FIELDS = ("body_sameframe", "geom_sameframe", "site_sameframe")

#: Controllers of floating-base robots: tt's batched whole-body kernels, or the oracle's mink
#: controller on the host (the reference).
FLOATING_CONTROLLERS = ("kernel", "mink")

#: Stand-in for an unlimited control range (float32-finite, as `tt.kernels.model.UNLIMITED`).
_UNLIMITED = 1.0e10


# --------------------------------------------------------------------------- batched model


def structure_key(model: mujoco.MjModel) -> tuple:
    """What must match for two MuJoCo models to share one `mjw.Model` (with per-world numbers).

    Every integer, boolean and enum array of the model (body tree, joint and geom types,
    contact bits, actuator kinds, sparsity patterns, ...) except `_IGNORED_INT_FIELDS`,
    and every physics option. Models with equal keys differ only in floating-point fields.
    Returns (digest of the integer arrays, their shapes, the options' bytes).
    """
    arrays = [getattr(model, name) for name in _int_fields()]
    digest = hashlib.sha1(b"".join(a.tobytes() for a in arrays)).hexdigest()
    opt = model.opt
    options = tuple(np.atleast_1d(getattr(opt, name)).tobytes() for name in _option_fields())
    return digest, tuple(a.shape for a in arrays), options


@functools.cache
def _int_fields() -> tuple[str, ...]:
    """Names of MjModel's integer / boolean arrays (the same for every model: MuJoCo fixes
    each field's type), less names and `_IGNORED_INT_FIELDS`."""
    probe = mujoco.MjModel.from_xml_string("<mujoco/>")
    return tuple(
        name for name in dir(probe)
        if not name.startswith(("_", "name")) and name not in _IGNORED_INT_FIELDS
        and isinstance(getattr(probe, name), np.ndarray) and getattr(probe, name).dtype.kind in "iub"
    )  # fmt: skip


@functools.cache
def _option_fields() -> tuple[str, ...]:
    """Names of MjOption's numeric fields."""
    opt = mujoco.MjModel.from_xml_string("<mujoco/>").opt
    return tuple(n for n in dir(opt) if not n.startswith("_") and isinstance(getattr(opt, n), (int, float, np.ndarray)))


def _batchable_fields() -> list[tuple[str, str | None]]:
    """(field name, owner) of the Model / Option array fields that may hold one entry per
    world; owner "opt" for options, None for the model."""
    import mujoco_warp as mjw

    out = []
    for cls, owner in ((mjw.Model, None), (mjw.Option, "opt")):
        for f in dataclasses.fields(cls):
            if tuple(getattr(f.type, "shape", ()))[:1] == ("*",):
                out.append((f.name, owner))
    return out


def batch_model(models: Sequence[mujoco.MjModel], *, device: str | None = None, check: bool = True):
    """One `mjw.Model` whose world w simulates ``models[w % len(models)]``.

    models: MuJoCo models of one `structure_key` (the same object may repeat).
    check: verify that the models share one structure (skip when the caller grouped them).
    Fields whose values are equal in every model stay shared (leading dim 1); fields that
    differ get a leading dimension of len(models). Raises ValueError naming the first model
    of another structure, or a differing field that MuJoCo-Warp does not store as
    MuJoCo does (so it cannot be filled from the MuJoCo models per world).
    """
    import mujoco_warp as mjw

    if len(models) == 0:
        raise TTError("models is empty; batch_model needs at least one MuJoCo model")
    keys = {}
    key0 = structure_key(models[0]) if check else None
    for i, m in enumerate(models if check else ()):
        key = keys.get(id(m))
        if key is None:
            key = keys[id(m)] = structure_key(m)
        if key != key0:
            raise TTError(
                f"model {i} ({model_name(m)!r}) has a different structure from model 0 (integer fields or "
                "options differ); group models by `structure_key` first"
            )
    with wp.ScopedDevice(device):
        batched = mjw.put_model(models[0])
        n = len(models)
        # One host read per distinct model object (worlds repeat designs).
        distinct = {id(m): m for m in models}
        order = [id(m) for m in models]
        for name, owner in _batchable_fields():
            target = batched.opt if owner == "opt" else batched
            array = getattr(target, name, None)
            if array is None or array.shape[0] != 1:
                continue
            source0 = models[0].opt if owner == "opt" else models[0]
            if not hasattr(source0, name):
                continue  # derived by put_model from options (impratio_invsqrt), which the key fixes
            host = {
                k: np.asarray(getattr(m.opt if owner == "opt" else m, name), dtype=np.float64)
                for k, m in distinct.items()
            }
            first = host[order[0]]
            if all(np.array_equal(v, first) for v in host.values()):
                continue
            shared = array.numpy()
            if first.size != shared.size or not np.allclose(first.reshape(shared.shape), shared, rtol=1e-6, atol=1e-6):
                raise TTError(
                    f"field {'opt.' if owner else ''}{name} differs between the models, but MuJoCo-Warp does not "
                    "store it as MuJoCo does, so it cannot be set per world"
                )
            stacked = np.stack([host[k].reshape(shared.shape[1:]) for k in order])
            setattr(
                target, name, wp.array(stacked.astype(shared.dtype), dtype=array.dtype, shape=(n,) + array.shape[1:])
            )
    return batched


# --------------------------------------------------------------------------- records


def records_episode(records: RecordArrays, D: int, M: int, nu: int, dt: float) -> Episode:
    """The Episode of `records` (zero-copy torch views), worlds design-major: D designs x M
    motions, nu the widest design's actuator count, dt the control period [s]."""
    f = {name: wp.to_torch(getattr(records, name)) for name in (f.name for f in dataclasses.fields(records))}
    for name in ("ctrl", "act_force", "act_vel"):
        f[name] = f[name][..., :nu]  # a design without actuators keeps one padding column
    tdev = f["qpos"].device
    return Episode(
        qpos=f["qpos"], qvel=f["qvel"], ctrl=f["ctrl"], action=f["ctrl"],
        act_force=f["act_force"], act_vel=f["act_vel"],
        ee_pos=f["ee_pos"], ee_quat=f["ee_quat"], target_pos=f["target_pos"], target_quat=f["target_quat"],
        alive=f["alive"], fallen=f["fallen"],
        design_index=torch.arange(D, device=tdev).repeat_interleave(M),
        motion_index=torch.arange(M, device=tdev).repeat(D),
        dt=dt,
    )  # fmt: skip


# --------------------------------------------------------------------------- inputs


def padded_motions(motions: Sequence[Motion], arms: int, control_dt: float, *, device: str):
    """`tt.kernels.rollout.MotionArrays` of M motions padded to the longest (last pose
    repeated); raises ValueError for a motion of another rate or arm count."""
    from tt.kernels.rollout import motion_arrays

    if len(motions) == 0:
        raise TTError("motions is empty; a rollout needs at least one motion")
    for j, motion in enumerate(motions):
        if not isinstance(motion, Motion):
            raise TypeError(f"motions[{j}] is a {type(motion).__name__}; expected tt.sim.motions.base.Motion")
        if abs(motion.dt - control_dt) > 1e-9:
            raise TTError(
                f"motions[{j}] ({motion.name!r}) has dt = {motion.dt} s; the controller runs at "
                f"control_dt = {control_dt} s and needs motions sampled at that period"
            )
        if motion.arms != arms:
            raise TTError(
                f"motions[{j}] ({motion.name!r}) has {motion.arms} arm(s); the designs have {arms} end effector(s)"
            )
    T = max(motion.steps for motion in motions)
    pos = np.zeros((len(motions), T, arms, 3))
    quat = np.zeros((len(motions), T, arms, 4))
    for j, motion in enumerate(motions):
        idx = np.minimum(np.arange(T), motion.steps - 1)
        pos[j], quat[j] = motion.pos[idx], motion.quat[idx]
    return motion_arrays(pos, quat, [motion.steps for motion in motions], device=device), T


def ctrl_ranges(models: Sequence[mujoco.MjModel]) -> np.ndarray:
    """Per-model actuator command clamp (lo, hi), +-1e10 where not ctrllimited (the oracle
    clips where ``actuator_ctrllimited``), (len(models), nu, 2) float32."""
    out = np.tile(np.array([-_UNLIMITED, _UNLIMITED], np.float32), (len(models), models[0].nu, 1))
    for i, m in enumerate(models):
        limited = m.actuator_ctrllimited.astype(bool)
        out[i, limited] = m.actuator_ctrlrange[limited]
    return out


# --------------------------------------------------------------------------- rollout


@dataclass
class _Group:
    """The worlds of one structure: their designs, rows in the Episode and simulation."""

    members: list[int]  # design indices
    rows: np.ndarray  # (Wg,) Episode rows, design-major
    floating: bool


def mjwarp_rollout(
    designs: Sequence[Design | mujoco.MjModel] | Robots,
    motions: Sequence[Motion],
    *,
    config: IKConfig = IKConfig(),
    wbc_config: WBCConfig = WBCConfig(),
    device: str | None = None,
    nconmax: int | None = None,
    njmax: int | None = None,
    progress: bool = False,
    floating_controller: str = "kernel",
    graph: bool | None = None,
) -> Episode:
    """Run every design on every motion on MuJoCo-Warp; an Episode of W = D * M worlds.

    designs: D tt Designs or MjModels with sites ``ee_0``, ... (or their `Robots`, as
        `tt.sim.backends.base.resolve_designs` gives them); fixed-base arms run the
        DiffIK of `config` (tt's batched kernel), floating-base legged robots the
        whole-body controller of `wbc_config`; a `WBCConfig` given as `config` is used as
        `wbc_config` too.
    motions: M motions sampled at the controller's control_dt, one arm per end effector.
    device: Warp device (None: `tt.kernels.device.default_device()`); the Episode lives there.
    nconmax, njmax: MuJoCo-Warp's contact and constraint capacity per world (None: its
        defaults for the model).
    floating_controller: "kernel" (tt's batched whole-body kernels, `tt.kernels.wbc`) or
        "mink" (the oracle's `WholeBodyController` on the host, world by world: the reference).
    graph: run each control step's physics (``substeps`` `mjw.step` and one `mjw.forward`,
        some hundred kernel launches) as one captured graph (`wp.ScopedCapture`), replayed
        every step; None (default): on a CUDA device yes, on the CPU plain launches; False:
        never. The controller and the records stay plain launches (they take the step index).
    Returns the oracle's Episode (`tt.sim.validate.oracle_rollout`): worlds design-major,
    joint fields zero-padded to the widest design, records repeated after termination.
    """
    from tt.kernels.device import resolve_device

    device = resolve_device(device)
    if floating_controller not in FLOATING_CONTROLLERS:
        raise TTError(f"floating_controller = {floating_controller!r}; expected one of {FLOATING_CONTROLLERS}")
    if isinstance(config, WBCConfig):
        wbc_config = config  # `tt.sim.rollout.rollout` passes one config for every backend
    robots = designs if isinstance(designs, Robots) else get_backend("mjwarp").resolve(designs)
    models, sites = list(robots.models), robots.ee_sites
    D, M, A = len(models), len(motions), len(sites)
    floating = [free_joint(m) is not None for m in models]
    for i, m in enumerate(models):
        cfg = wbc_config if floating[i] else config
        cfg.substeps(m)
        if floating[i]:
            foot_site_names(m)  # a floating base without feet raises here
        actuated_qpos(m)  # every actuator must drive a hinge or slide joint
    dts = {(wbc_config if floating[i] else config).control_dt for i in range(D)}
    if len(dts) > 1:
        raise TTError(f"IKConfig.control_dt and WBCConfig.control_dt differ ({sorted(dts)}); one batch needs one rate")
    control_dt = dts.pop()
    marrays, T = padded_motions(motions, A, control_dt, device=device)

    # Structure groups refine tt's topology groups (`tt.kernels.model.topology_key`): one
    # `mjw.Model` and one IK kernel launch each.
    groups: dict[tuple, _Group] = {}
    for d, m in enumerate(models):
        key = (structure_key(m), tuple(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s) for s in sites))
        g = groups.setdefault(key, _Group([], np.zeros(0, np.int64), floating[d]))
        g.members.append(d)
    for g in groups.values():
        g.rows = np.array([d * M + j for d in g.members for j in range(M)], dtype=np.int64)
    logger.debug("mjwarp rollout: %d designs in %d structure group(s), %d motions, T=%d", D, len(groups), M, T)

    records = RecordArrays.zeros(
        D * M, T, max(m.nq for m in models), max(m.nv for m in models), max(m.nu for m in models), A, device=device
    )
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T * len(groups), desc="mjwarp", unit="step")
    for g in groups.values():
        with wp.ScopedDevice(device):
            _run_group(
                [models[d] for d in g.members for _ in range(M)], g, sites=sites, motions=marrays, steps=T,
                motion_count=M, config=wbc_config if g.floating else config, records=records, device=device,
                nconmax=nconmax, njmax=njmax, bar=bar, floating_controller=floating_controller,
                graph=wp.get_device(device).is_cuda if graph is None else bool(graph),
            )  # fmt: skip
    if bar is not None:
        bar.close()
    return records_episode(records, D, M, max(m.nu for m in models), control_dt)


def _ik_model(m: mujoco.MjModel) -> mujoco.MjModel:
    """`m`, or a copy of it with contacts disabled: tt's IK kernel reads only the kinematic
    tree, and its `TreeModel` refuses models with contacts (which MuJoCo-Warp simulates)."""
    if m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
        return m
    kinematic = copy.deepcopy(m)
    kinematic.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    return kinematic


def _run_group(
    group_models: list[mujoco.MjModel],
    g: _Group,
    *,
    sites: tuple[str, ...],
    motions,
    steps: int,
    motion_count: int,
    config: IKConfig,
    records: RecordArrays,
    device: str,
    nconmax: int | None,
    njmax: int | None,
    bar,
    floating_controller: str = "kernel",
    graph: bool = False,
) -> None:
    """Simulate the Wg worlds of one structure group (world i: ``group_models[i]`` on motion
    ``i % motion_count``) and write their records into rows ``g.rows``."""
    import mujoco_warp as mjw

    from tt.kernels.control import joint_command, live_joint_command, lookahead_targets
    from tt.kernels.ik import ik_step
    from tt.kernels.model import build_tree_model
    from tt.kernels.records import record_step, site_poses
    from tt.kernels.rollout import start_postures
    from tt.kernels.wbc import make_wbc_data, wbc_initial_q, wbc_step
    from tt.sim.wbc_model import build_wbc_model

    m0 = group_models[0]
    Wg, A = len(group_models), len(sites)
    substeps = config.substeps(m0)
    model = batch_model(group_models, device=device, check=False)
    data = mjw.make_data(m0, nworld=Wg, nconmax=nconmax, njmax=njmax)
    world_row = wp.array(g.rows.astype(np.int32), dtype=int, device=device)
    world_motion = wp.array((np.arange(Wg) % motion_count).astype(np.int32), dtype=int, device=device)
    site_ids = wp.array([mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_SITE, s) for s in sites], dtype=int, device=device)
    act_qpos = actuated_qpos(m0)
    target_pos = wp.zeros((Wg, A), dtype=wp.vec3, device=device)
    target_quat = wp.zeros((Wg, A), dtype=wp.vec4, device=device)
    ee_pos = wp.zeros((Wg, A), dtype=wp.vec3, device=device)
    ee_quat = wp.zeros((Wg, A), dtype=wp.vec4, device=device)
    base_qpos, fall_height = -1, None

    if g.floating:
        joint = free_joint(m0)
        base_qpos = int(m0.jnt_qposadr[joint])
        heights = [config.fall_height_fraction * standing_height(m) for m in group_models]
        fall_height = wp.array(np.array(heights, np.float32), dtype=float, device=device)
        key = mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_KEY, HOME_KEY)
        if key >= 0:
            data.ctrl.assign(np.stack([m.key_ctrl[key] for m in group_models]).astype(np.float32))
        world_motions = np.arange(Wg) % motion_count
        if floating_controller == "mink":
            # The oracle's whole-body controller, one per design, on the host.
            designs = {id(m): m for m in group_models}
            controllers = {k: WholeBodyController(m, config) for k, m in designs.items()}
            first_pos, first_quat = motions.first_pos.numpy(), motions.first_quat.numpy()
            qpos0 = np.stack([
                controllers[id(m)].initial_q(first_pos[i % motion_count], first_quat[i % motion_count])
                for i, m in enumerate(group_models)
            ])  # fmt: skip
            motion_pos, motion_quat, motion_steps = motions.pos.numpy(), motions.quat.numpy(), motions.steps.numpy()
            limited = [m.actuator_ctrllimited.astype(bool) for m in group_models]
            ranges = [m.actuator_ctrlrange for m in group_models]
            ctrl = np.zeros((Wg, m0.nu))
        else:
            wbc = build_wbc_model(group_models, config, device=device)
            wbc_data = make_wbc_data(wbc, Wg, device=device)
            first_pos = wp.array(motions.first_pos.numpy()[world_motions], dtype=wp.vec3d, device=device)
            first_quat = wp.array(motions.first_quat.numpy()[world_motions], dtype=wp.vec4d, device=device)
            qpos0 = wbc_initial_q(
                wbc, first_pos, first_quat, config.init_iterations, data=wbc_data, device=device
            ).numpy()
            ranges_w = wp.array(ctrl_ranges(group_models), dtype=wp.vec2, device=device)
            act_qpos_w = wp.array(act_qpos.astype(np.int32), dtype=int, device=device)
            q_cmd = wp.zeros((Wg, m0.nq), dtype=float, device=device)
        data.qpos.assign(qpos0.astype(np.float32))
    else:
        kinematic = {id(m): _ik_model(m) for m in group_models}
        tree = build_tree_model([kinematic[id(m)] for m in group_models], sites, device=device)
        weights = config.ik_weights()
        wp.copy(
            data.qpos, start_postures(tree, motions, config.init_ik_weights(), config.init_iterations, device=device)
        )
        ranges_w = wp.array(ctrl_ranges(group_models), dtype=wp.vec2, device=device)
        act_qpos_w = wp.array(act_qpos.astype(np.int32), dtype=int, device=device)
        q_cmd = wp.zeros((Wg, m0.nq), dtype=float, device=device)
    data.qvel.zero_()

    def physics() -> None:
        for _ in range(substeps):
            mjw.step(model, data)
        mjw.forward(model, data)

    if graph:
        # Captured, not run: the replay at each step does the work. A first uncaptured step
        # would load MuJoCo-Warp's modules, but it would also move the state, so they load
        # inside the capture (CUDA 12.3+ drivers allow it; CPU captures always do).
        with wp.ScopedCapture(device=device) as capture:
            physics()
        physics_graph = capture.graph

    for t in range(steps):
        if g.floating and floating_controller == "kernel":
            lookahead_targets(t, config.lookahead_steps, world_motion, motions, target_pos, target_quat, device=device)
            wbc_step(wbc, data.qpos, target_pos, target_quat, q_cmd, data=wbc_data, device=device)
            live_joint_command(q_cmd, act_qpos_w, ranges_w, t, world_row, records.alive, data.ctrl, device=device)
        elif g.floating:
            q = data.qpos.numpy().astype(np.float64)
            # Terminated worlds keep their last command: the oracle stops them, and mink
            # should not see a state that may have diverged.
            alive = records.alive.numpy()[g.rows, t - 1] if t > 0 else np.ones(Wg, bool)
            for i, m in enumerate(group_models):
                if not alive[i]:
                    continue
                j = i % motion_count
                goal = min(t + config.lookahead_steps, int(motion_steps[j]) - 1)
                q_cmd_i = controllers[id(m)].step(q[i], motion_pos[j, goal], motion_quat[j, goal])
                c = q_cmd_i[act_qpos]
                c[limited[i]] = np.clip(c[limited[i]], ranges[i][limited[i], 0], ranges[i][limited[i], 1])
                ctrl[i] = c
            data.ctrl.assign(ctrl.astype(np.float32))
        else:
            lookahead_targets(t, config.lookahead_steps, world_motion, motions, target_pos, target_quat, device=device)
            ik_step(tree, data.qpos, target_pos, target_quat, weights, q_cmd, device=device)
            joint_command(q_cmd, act_qpos_w, ranges_w, data.ctrl, device=device)
        if graph:
            wp.capture_launch(physics_graph)
        else:
            physics()
        site_poses(site_ids, data.site_xpos, data.site_xmat, ee_pos, ee_quat, device=device)
        record_step(
            records, t, threshold=config.termination_pos_error, world_row=world_row, world_motion=world_motion,
            motions=motions, qpos=data.qpos, qvel=data.qvel, ctrl=data.ctrl, act_force=data.actuator_force,
            act_vel=data.actuator_velocity, ee_pos=ee_pos, ee_quat=ee_quat, base_qpos=base_qpos,
            fall_height=fall_height, fall_tilt=getattr(config, "fall_tilt", math.pi), device=device,
        )  # fmt: skip
        if bar is not None:
            bar.update(1)


# --------------------------------------------------------------------------- open loop


def mjwarp_simulate(
    models: Sequence[mujoco.MjModel],
    ctrl: np.ndarray,
    *,
    qpos: np.ndarray | None = None,
    qvel: np.ndarray | None = None,
    device: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Open-loop simulation of W models under given actuator commands, one physics step each.

    models: W MuJoCo models (any mix of structures; each structure is one batched model).
    ctrl: commands per physics step, (W, S, NU) with NU >= every model's nu (extra columns
        ignored). qpos, qvel: initial state (W, NQ), (W, NV) zero-padded (None: qpos0, rest).
    Returns qpos (W, S + 1, NQ) and qvel (W, S + 1, NV) float64 (entry 0: the initial state,
    entry s: after s steps), zero-padded to the widest model.
    """
    import mujoco_warp as mjw

    from tt.kernels.device import resolve_device

    device = resolve_device(device)
    W = len(models)
    ctrl = np.asarray(ctrl, dtype=np.float64)
    nq, nv, nu = (max(getattr(m, k) for m in models) for k in ("nq", "nv", "nu"))
    if ctrl.ndim != 3 or ctrl.shape[0] != W or ctrl.shape[2] < nu:
        raise TTError(f"ctrl has shape {ctrl.shape}; expected (W={W}, S, >= {nu})")
    S = ctrl.shape[1]
    qpos_out = np.zeros((W, S + 1, nq))
    qvel_out = np.zeros((W, S + 1, nv))
    groups: dict[tuple, list[int]] = {}
    for i, m in enumerate(models):
        groups.setdefault(structure_key(m), []).append(i)
    for members in groups.values():
        m0 = models[members[0]]
        with wp.ScopedDevice(device):
            model = batch_model([models[i] for i in members], device=device)
            data = mjw.make_data(m0, nworld=len(members))
            q0 = np.stack([m0.qpos0 if qpos is None else qpos[i, : m0.nq] for i in members])
            v0 = np.zeros((len(members), m0.nv)) if qvel is None else np.stack([qvel[i, : m0.nv] for i in members])
            data.qpos.assign(q0.astype(np.float32))
            data.qvel.assign(v0.astype(np.float32))
            c = wp.array(ctrl[members][:, :, : m0.nu].astype(np.float32), dtype=float, device=device)
            traj_q = [data.qpos.numpy().astype(np.float64)]
            traj_v = [data.qvel.numpy().astype(np.float64)]
            for s in range(S):
                wp.copy(data.ctrl, c[:, s])
                mjw.step(model, data)
                traj_q.append(data.qpos.numpy().astype(np.float64))
                traj_v.append(data.qvel.numpy().astype(np.float64))
        qpos_out[members, :, : m0.nq] = np.stack(traj_q, axis=1)
        qvel_out[members, :, : m0.nv] = np.stack(traj_v, axis=1)
    return qpos_out, qvel_out


__all__ = [
    "FLOATING_CONTROLLERS",
    "batch_model",
    "ctrl_ranges",
    "mjwarp_rollout",
    "mjwarp_simulate",
    "padded_motions",
    "records_episode",
    "structure_key",
]
