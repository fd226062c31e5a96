"""Differentiable-simulation gradients, for the guidance ablation ``--sim-grad-weight lambda``.

The simulator's gradient of a candidate's reward, in three links:

1. Design -> model fields. A design's continuous choices c (link lengths, offsets, ...)
   build an MJCF, MuJoCo compiles it, and tt's Warp kernels read the compiled model as
   the members of the `tt.kernels.model.TreeArrays` struct (body offsets, masses,
   inertias, joint axes, gains, site poses: `ENTITY_FIELDS`, taken from the struct) and
   of `Kinematics64` (the float64 kinematic copies the start posture is solved with),
   plus the robot's size and mass. The compiler is not differentiable, so the Jacobian
   dF/dc comes from central differences of the compile (step 1e-4 of each choice's range,
   kept inside the bounds); F(c) = F(c0) + dF/dc (c - c0) around the candidate.
2. Fields -> reward. `WarpFunction` runs the differentiable fused rollout
   (`tt.kernels.rollout.rollout_tree(differentiable=True)`: start posture, DiffIK
   tracking, physics) on a `wp.Tape` as a `torch.autograd.Function`: torch tensors enter
   as Warp arrays sharing their memory (`wp.from_torch`), the records come back as torch
   views of the Warp arrays (`wp.to_torch`), and backward hands the records' adjoints to
   `Tape.backward` and returns the fields' gradients, again as views. The reward is
   `tt.sim.rewards.evaluate` on those records (the one definition; full motion length,
   exact termination), averaged over motions; autograd carries dR/dF to dR/dc.
3. Choices -> tokens. A candidate's tokens decode to c by least squares on its encoded
   continuous token values e (`tt.tokens.design_from_tokens`); linearised, c moves by
   (J^T J)^+ J^T de with J = de/dc (central differences of the tokenizer), so the gradient
   in encoded token space is J (J^T J)^+ dR/dc, and in normalised space it is scaled by
   each feature's half range. Its directional derivative along any token change the
   design can produce equals dR/dc along the matching change of c.

`SimGradient.token_gradient` does all three for every candidate of a guided step (each
decoded with `tt.guidance.zeroth.DesignDecoder` to a design of exactly its token structure,
no projection; a candidate that does not decode gets a zero gradient and is counted) and
`tt.guidance.selfguide` mixes it into the guidance gradient. Cost: per guided step, one
least-squares decode per candidate (CPU, seconds), 2 p compiles for the Jacobians, and one
differentiable rollout of candidates x motions, whose memory grows with steps x substeps;
`DGSConfig.sim_grad_start` limits it to the late steps. Contact-free spaces only (tt's Warp
rollout has no contacts).
"""

from __future__ import annotations

import abc
import logging
import warnings
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
import warp as wp

from tt.dit.checkpoint import TrainedModel
from tt.guidance.stencil import central_points, choice_bounds
from tt.kernels.errors import TTError
from tt.kernels.model import ENTITY_FIELDS, KINEMATICS64_FIELDS
from tt.sim.controller import IKConfig
from tt.sim.designs import Design, DesignSpace, get_space
from tt.sim.motions.base import Motion
from tt.sim.rewards import RewardConfig, RewardInputs, evaluate, robot_mass, robot_size

log = logging.getLogger(__name__)

#: `tt.kernels.model.TreeArrays` members (float32) that may depend on a design's continuous
#: choices: every per-body, per-dof, per-actuator and per-end-effector field (the struct is
#: the one list; gravity, timestep and the limit flags are per-world options).
FIELDS = ENTITY_FIELDS
#: Float64 kinematic copies (`TreeModel.kinematics64`, `Kinematics64`) the start posture reads.
FIELDS64 = KINEMATICS64_FIELDS
#: Quaternion fields (q and -q are one rotation; differences align their signs first).
_QUATS = ("body_quat", "body_iquat", "ee_quat")
#: Finite-difference step as a fraction of each continuous choice's range.
REL_STEP = 1e-4


# ------------------------------------------------------------------------------ the boundary
class WarpProgram(abc.ABC):
    """What `WarpFunction` runs: `record(arrays) -> outputs` launches Warp kernels that read
    `arrays` (one per input tensor, of the Warp dtypes `dtypes`) and returns Warp arrays;
    the launches are recorded on a tape. Outputs whose dtype is not a float type come back
    as non-differentiable tensors."""

    dtypes: Sequence[type] = ()

    @abc.abstractmethod
    def record(self, arrays: list[wp.array]) -> list[wp.array]:
        """Launch the program's kernels on `arrays`; return its output arrays."""


def _float_dtype(dtype) -> bool:
    scalar = getattr(dtype, "_wp_scalar_type_", dtype)
    return scalar in (wp.float16, wp.float32, wp.float64)


class WarpFunction(torch.autograd.Function):
    """torch autograd through Warp kernels: ``outputs = WarpFunction.apply(program, *inputs)``.

    Inputs are torch tensors on the Warp device's torch twin; each enters Warp without a
    copy (`wp.from_torch`, with a gradient buffer). Outputs are torch views of the Warp
    output arrays. Backward copies the outputs' adjoints into their Warp gradient buffers,
    runs `Tape.backward` and returns views of the inputs' Warp gradients. One backward per
    forward (the tape is released after it).
    """

    @staticmethod
    def forward(ctx, program: WarpProgram, *inputs: torch.Tensor):
        wp.init()
        tensors = [t.detach().contiguous() for t in inputs]
        # Python's float stands for float32 in Warp signatures; from_torch wants the Warp type.
        dtypes = [wp.float32 if dt is float else dt for dt in program.dtypes]
        arrays = [wp.from_torch(t, dtype=dt, requires_grad=True) for t, dt in zip(tensors, dtypes)]
        tape = wp.Tape()
        with tape:
            outputs = program.record(arrays)
        results = [wp.to_torch(o, requires_grad=False) for o in outputs]
        ctx.tape, ctx.arrays, ctx.tensors, ctx.outputs = tape, arrays, tensors, outputs
        ctx.mark_non_differentiable(*[r for r, o in zip(results, outputs) if not _float_dtype(o.dtype)])
        return tuple(results)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor):
        if ctx.tape is None:
            raise RuntimeError("WarpFunction supports one backward pass per forward")
        adjoints = {}
        for o, g in zip(ctx.outputs, grads):
            if g is None or not _float_dtype(o.dtype) or o.grad is None:
                continue
            adjoints[o] = wp.from_torch(g.contiguous().to(wp.to_torch(o, requires_grad=False).dtype), dtype=o.dtype)
        ctx.tape.backward(grads=adjoints)
        out = [wp.to_torch(a.grad, requires_grad=False) for a in ctx.arrays]
        ctx.tape = None
        return (None, *out)


# ------------------------------------------------------------------------------ design -> fields
@dataclass
class FieldJacobian:
    """Fields of one design and their derivatives with respect to its continuous choices.

    fields: name -> value (one world), for ``FIELDS`` and ``("64", name)`` for ``FIELDS64``,
    plus "size" [m] and "mass" [kg]; jacobian: the same keys -> (p, *shape) dF/dc.
    """

    design: Design
    fields: dict
    jacobian: dict


def design_stencil(space: DesignSpace, design: Design, rel_step: float) -> tuple[list[Design], np.ndarray]:
    """Designs c0 + h e_j and c0 - h e_j (kept in bounds; h a share ``rel_step`` of each
    range) for every choice j, in the order (+, -) per j, and each pair's width
    (`tt.guidance.stencil.central_points`)."""
    lo, hi = choice_bounds(space, design)
    points, width = central_points(design.continuous, rel_step * np.maximum(hi - lo, 1e-12), lo, hi)
    return [Design(design.space, design.discrete, tuple(float(x) for x in c)) for c in points], width


def _host_fields(tree, models) -> dict:
    """Per-world host copies of the differentiable fields, size and mass (one row per model)."""
    out = {name: getattr(tree.arrays, name).numpy().astype(np.float64) for name in FIELDS}
    out.update({("64", name): getattr(tree.kinematics64, name).numpy() for name in FIELDS64})
    out["size"] = robot_size(models, dtype=torch.float64).numpy()
    out["mass"] = robot_mass(models, dtype=torch.float64).numpy()
    return out


def field_jacobian(
    space: DesignSpace,
    design: Design,
    sites: Sequence[str],
    *,
    rel_step: float = REL_STEP,
    device: str = "cpu",
    derivatives: bool = True,
) -> FieldJacobian:
    """`FieldJacobian` of `design` by central differences of the MJCF compile (module
    docstring); derivatives=False: the fields only, with zero derivatives (no extra compiles)."""
    from tt.kernels.model import build_tree_model

    stencil, span = design_stencil(space, design, rel_step) if derivatives else ([], np.zeros(len(design.continuous)))
    models = [space.model(design)] + [space.model(d) for d in stencil]
    tree = build_tree_model(models, sites, device=device)
    host = _host_fields(tree, models)
    fields = {k: v[0] for k, v in host.items()}
    p = len(design.continuous)
    if not derivatives:
        return FieldJacobian(design, fields, {k: np.zeros((p, *np.shape(v))) for k, v in fields.items()})
    jac = {}
    for k, v in host.items():
        plus, minus = v[1::2], v[2::2]  # (p, ...)
        name = k[1] if isinstance(k, tuple) else k
        if name in _QUATS:
            flip = (plus * minus).sum(-1, keepdims=True) < 0
            minus = np.where(flip, -minus, minus)
        jac[k] = (plus - minus) / span.reshape(p, *([1] * (v.ndim - 1)))
    return FieldJacobian(design, fields, jac)


# ------------------------------------------------------------------------------ fields -> reward
class _Rollout(WarpProgram):
    """The differentiable rollout of one topology group as a `WarpProgram`: inputs are the
    ``FIELDS`` then the ``FIELDS64`` of every world; outputs ee_pos, ee_quat, act_force,
    act_vel (differentiable), alive, target_pos, target_quat."""

    def __init__(self, tree, motions, steps: int, config: IKConfig, device: str):
        self.tree, self.motions, self.steps, self.config, self.device = tree, motions, steps, config, device
        self.dtypes = [getattr(tree.arrays, n).dtype for n in FIELDS] + [
            getattr(tree.kinematics64, n).dtype for n in FIELDS64
        ]

    def record(self, arrays: list[wp.array]) -> list[wp.array]:
        from tt.kernels.rollout import rollout_tree

        k = len(FIELDS)
        # The arrays come from `WarpFunction` with requires_grad set, so the new structs
        # carry their gradients.
        model = self.tree.with_fields(dict(zip(FIELDS, arrays[:k])), dict(zip(FIELDS64, arrays[k:])))
        out = rollout_tree(
            model,
            self.motions,
            self.tree.world_count,
            self.steps,
            **self.config.rollout_args(),
            differentiable=True,
            device=self.device,
        )
        return [out.ee_pos, out.ee_quat, out.act_force, out.act_vel, out.alive, out.target_pos, out.target_quat]


@dataclass
class DesignGradient:
    """Simulated reward of D designs and its gradient with respect to their continuous choices.

    reward: (D,) mean over motions (the chosen alphas); grad: per design (p_d,) dR/dc;
    rollouts: worlds simulated.
    """

    reward: np.ndarray
    grad: list[np.ndarray]
    rollouts: int


def _motion_host(motions: Sequence[Motion]) -> tuple[np.ndarray, np.ndarray, list[int]]:
    T = max(m.steps for m in motions)
    pos = np.stack([m.pos[np.minimum(np.arange(T), m.steps - 1)] for m in motions])
    quat = np.stack([m.quat[np.minimum(np.arange(T), m.steps - 1)] for m in motions])
    return pos, quat, [m.steps for m in motions]


def design_reward_gradient(
    space: DesignSpace | str,
    designs: Sequence[Design],
    motions: Sequence[Motion],
    cfg: RewardConfig,
    *,
    guidance: bool = True,
    gradient: bool = True,
    jacobians: Sequence[FieldJacobian] | None = None,
    config: IKConfig = IKConfig(),
    rel_step: float = REL_STEP,
    device: str | None = None,
) -> DesignGradient:
    """Reward `cfg` of each design on `motions` from a differentiable Warp rollout and, with
    `gradient`, dR/dc (see the module docstring). guidance: use the guidance alphas;
    jacobians: precomputed `field_jacobian`s of the designs (else computed here)."""
    from tt.kernels.device import resolve_device
    from tt.kernels.model import build_tree_model, topology_key
    from tt.kernels.rollout import motion_arrays

    space = get_space(space) if isinstance(space, str) else space
    if space.has_contacts:
        raise TTError(
            f"design space {space.name!r} has contacts; the differentiable Warp rollout simulates "
            "contact-free trees only"
        )
    device = resolve_device(device)
    tdev = wp.device_to_torch(device)
    sites = space.ee_sites()
    M = len(motions)
    pos, quat, lengths = _motion_host(motions)
    marrays = motion_arrays(pos, quat, lengths, device=device)
    T = pos.shape[1]
    models = [space.model(d) for d in designs]
    if jacobians is None:
        jacobians = [
            field_jacobian(space, d, sites, rel_step=rel_step, device=device, derivatives=gradient) for d in designs
        ]
    jacs = list(jacobians)
    groups: dict[tuple, list[int]] = {}
    for i, m in enumerate(models):
        groups.setdefault(topology_key(m, sites), []).append(i)
    reward = np.zeros(len(designs))
    grads: list[np.ndarray] = [np.zeros(len(d.continuous)) for d in designs]
    motion_steps = torch.tensor(lengths, device=tdev)
    for members in groups.values():
        tree = build_tree_model([models[i] for i in members for _ in range(M)], sites, device=device)
        cs, fields = [], {k: [] for k in jacs[members[0]].fields}
        with torch.enable_grad():
            for i in members:
                j = jacs[i]
                c0 = torch.tensor(designs[i].continuous, dtype=torch.float64, device=tdev)
                c = c0.clone().requires_grad_(gradient)
                cs.append(c)
                for k, v in j.fields.items():
                    base = torch.as_tensor(v, dtype=torch.float64, device=tdev)
                    d = torch.as_tensor(j.jacobian[k], dtype=torch.float64, device=tdev)
                    value = base + torch.tensordot(c - c0, d, dims=1)
                    fields[k].append(value.expand(M, *value.shape))
            flat = {k: torch.cat(v) for k, v in fields.items()}  # (W, ...) design-major
            inputs = [flat[n].float() for n in FIELDS] + [flat[("64", n)] for n in FIELDS64]
            program = _Rollout(tree, marrays, T, config, device)
            ee_pos, ee_quat, force, vel, alive, tpos, tquat = WarpFunction.apply(program, *inputs)
            nu = models[members[0]].nu
            inp = RewardInputs(
                ee_pos=ee_pos.double(),
                ee_quat=ee_quat.double(),
                target_pos=tpos.double(),
                target_quat=tquat.double(),
                act_force=force[..., :nu].double(),
                act_vel=vel[..., :nu].double(),
                size=flat["size"],
                mass=flat["mass"],
                alive=alive,
                motion_steps=motion_steps.repeat(len(members)),
            )
            per_world = evaluate(inp, cfg, guidance=guidance).reward.reshape(len(members), M).mean(1)  # (D_group,)
            if gradient:
                g = torch.autograd.grad(per_world.sum(), cs, allow_unused=True)
        for k, i in enumerate(members):
            reward[i] = float(per_world[k].detach())
            if gradient and g[k] is not None:
                grads[i] = g[k].detach().cpu().numpy()
        log.debug("differentiable rollout: %d designs x %d motions, %d steps", len(members), M, T)
    return DesignGradient(reward, grads, len(designs) * M)


# ------------------------------------------------------------------------------ choices -> tokens
def encoded_tokens(space: DesignSpace, designs: Sequence[Design]) -> list[dict[str, np.ndarray]]:
    """Encoded embodiment tokens of each design's real slots, type -> (n_real, width), float64."""
    from tt.tokens.tokenize import TokenizeConfig, TokenizeWarning, tokenize_models

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TokenizeWarning)
        batch = tokenize_models([space.model(d) for d in designs], TokenizeConfig(dtype=np.float64)).tokens
    out = []
    for i in range(len(designs)):
        out.append({n: np.asarray(batch.values[n][i])[np.asarray(batch.mask[n][i], dtype=bool)] for n in batch.types})
    return out


def token_jacobian(space: DesignSpace, design: Design, *, rel_step: float = REL_STEP) -> dict[str, np.ndarray]:
    """d(encoded real embodiment tokens)/dc by central differences of the tokenizer: type ->
    (p, n_real, width)."""
    stencil, span = design_stencil(space, design, rel_step)
    toks = encoded_tokens(space, stencil)
    p = len(design.continuous)
    return {n: np.stack([(toks[2 * j][n] - toks[2 * j + 1][n]) / span[j] for j in range(p)]) for n in toks[0]}


def tokens_from_choice_gradient(jacobian: dict[str, np.ndarray], grad_c: np.ndarray) -> dict[str, np.ndarray]:
    """The gradient in encoded token space of the least-squares decode: J (J^T J)^+ dR/dc,
    type -> (n_real, width) (see the module docstring)."""
    names = list(jacobian)
    J = np.concatenate([jacobian[n].reshape(jacobian[n].shape[0], -1) for n in names], 1).T  # (N, p)
    flat = J @ (np.linalg.pinv(J.T @ J) @ grad_c)  # (N,)
    out, start = {}, 0
    for n in names:
        size = int(np.prod(jacobian[n].shape[1:]))
        out[n] = flat[start : start + size].reshape(jacobian[n].shape[1:])
        start += size
    return out


# ------------------------------------------------------------------------------ guidance
@dataclass
class SimStats:
    """steps: guided steps the simulator gradient ran at; candidates: candidate-steps decoded
    and simulated; decode_failures: candidate-steps that did not decode (zero gradient);
    rollouts: worlds simulated."""

    steps: int = 0
    candidates: int = 0
    decode_failures: int = 0
    rollouts: int = 0


class SimGradient:
    """The simulator gradient in normalised token space for DGS (`token_gradient`).

    space: design space (contact-free); cfg: the reward (its guidance alphas are used);
    trained: the model (layout and normaliser); decoder: candidate decoder (default
    `tt.guidance.zeroth.DesignDecoder` with ``max_distance=0``); start_step: guided steps before it get no simulator
    gradient; device: Warp device for the rollouts.
    """

    def __init__(
        self,
        space: DesignSpace | str,
        cfg: RewardConfig,
        trained: TrainedModel,
        *,
        decoder: Callable | None = None,
        start_step: int = 0,
        device: str | None = None,
        config: IKConfig = IKConfig(),
        rel_step: float = REL_STEP,
    ):
        from tt.guidance.zeroth import DesignDecoder

        self.space = get_space(space) if isinstance(space, str) else space
        if self.space.has_contacts:
            raise TTError(f"--sim-grad-weight needs a contact-free design space; {self.space.name!r} has contacts")
        self.cfg, self.trained = cfg, trained
        # Exact structures only: the token gradient is mapped onto the candidate's own tokens,
        # so the decoded design must have them (a projected design has other tokens).
        self.decoder = decoder if decoder is not None else DesignDecoder(self.space, max_distance=0)
        self.start_step, self.device, self.config, self.rel_step = int(start_step), device, config, rel_step
        self.stats = SimStats()

    def summary(self) -> dict:
        s = self.stats
        return {
            "steps": s.steps,
            "candidates": s.candidates,
            "decode_failures": s.decode_failures,
            "rollouts": s.rollouts,
        }

    def token_gradient(self, ctx, x0: dict[str, torch.Tensor], step: int) -> dict[str, torch.Tensor]:
        """dR_sim/dx0 for the embodiment types of `x0` (normalised, (n, L, D) each); zero for
        candidates that do not decode and before `start_step`."""
        from tt.guidance.zeroth import decode_x0

        out = {n: torch.zeros_like(v) for n, v in x0.items()}
        if step < self.start_step:
            return out
        norm = self.trained.normalizer
        decoded = decode_x0(self.trained.layout, norm, x0, ctx.queries[0].tokens, self.decoder)
        n = len(decoded)
        ok = [i for i in range(n) if decoded[i].design is not None]
        self.stats.steps += 1
        self.stats.decode_failures += n - len(ok)
        if not ok:
            return out
        designs = [decoded[i].design for i in ok]
        result = design_reward_gradient(
            self.space,
            designs,
            ctx.motions,
            self.cfg,
            guidance=True,
            config=self.config,
            rel_step=self.rel_step,
            device=self.device,
        )
        self.stats.candidates += len(ok)
        self.stats.rollouts += result.rollouts
        for k, i in enumerate(ok):
            grad_e = tokens_from_choice_gradient(
                token_jacobian(self.space, designs[k], rel_step=self.rel_step), result.grad[k]
            )
            place_token_gradient(out, i, grad_e, norm, real_slots(x0, i))
        return out


def real_slots(x0: dict[str, torch.Tensor], i: int) -> dict[str, torch.Tensor]:
    """type -> (L,) bool: the slots candidate i of x0 (normalised, (n, L, width)) does not pad."""
    from tt.tokens.normalize import is_padding

    return {name: ~is_padding(v[i]) for name, v in x0.items()}


def place_token_gradient(
    out: dict[str, torch.Tensor],
    i: int,
    grad_e: dict[str, np.ndarray],
    normalizer,
    real: dict[str, torch.Tensor],
    *,
    add: bool = False,
) -> None:
    """Write candidate i's gradient in encoded token space (`tokens_from_choice_gradient`:
    type -> (n_real, width)) into `out` (normalised units, type -> (n, L, width)) at the
    slots `real` marks (type -> (L,) bool; `real_slots` of the candidate itself, or of the
    design it decodes to), in order; add: add to what is there instead of replacing it."""
    for name, g in grad_e.items():
        if name not in out:
            continue
        slots = real[name].to(out[name].device)
        if int(slots.sum()) != g.shape[0]:
            raise RuntimeError(f"candidate {i}: {int(slots.sum())} real {name} tokens but its design has {g.shape[0]}")
        # The normaliser is affine per feature: de/dx is the raw change of a unit step.
        unit = torch.ones(1, out[name].shape[-1], dtype=torch.float64)
        de_dx = (normalizer.denormalize_values(name, unit) - normalizer.denormalize_values(name, 0 * unit))[0]
        value = (torch.as_tensor(g, dtype=torch.float64) * de_dx).to(device=out[name].device, dtype=out[name].dtype)
        out[name][i, slots] = out[name][i, slots] + value if add else value  # dR/dx = dR/de de/dx


__all__ = [
    "FIELDS",
    "FIELDS64",
    "REL_STEP",
    "DesignGradient",
    "FieldJacobian",
    "SimGradient",
    "SimStats",
    "WarpFunction",
    "WarpProgram",
    "design_reward_gradient",
    "design_stencil",
    "encoded_tokens",
    "field_jacobian",
    "place_token_gradient",
    "real_slots",
    "token_jacobian",
    "tokens_from_choice_gradient",
]
