"""Differentiable-simulation gradients (`tt.guidance.simgrad`) and their mixing into DGS.

References: torch autograd of the same function for the Warp/torch boundary; hand
derivatives of a two-link arm's compiled fields (offsets, masses, size); the tokenizer
itself for the choices-to-tokens map (a linearised decode must recover a perturbation);
central differences of the simulated reward for the whole chain (the first call compiles
the differentiable rollout of the planar arm, ~30 s on a loaded 2-core CPU with an empty
Warp kernel cache; a few seconds once cached).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import warp as wp

from tt.guidance.simgrad import (
    WarpFunction,
    WarpProgram,
    design_reward_gradient,
    encoded_tokens,
    field_jacobian,
    token_jacobian,
    tokens_from_choice_gradient,
)
from tt.sim.designs import Design, get_space
from tt.sim.designs.base import ContinuousParam, DesignSpace
from tt.sim.motions.base import Motion
from tt.sim.rewards import RewardConfig, RewardInputs, evaluate, robot_mass, robot_size
from tt.sim.validate import oracle_rollout

wp.config.quiet = True
DENSITY = 1000.0  # [kg/m^3]


class PlanarArm(DesignSpace):
    """Two capsule links on hinges about z, bent 90 degrees at home; choices l1, l2 [m] and
    the capsules' radius [m]. Contact-free, position servos, ee_0 at the tip."""

    name = "planar_arm"
    ee_count = 1

    def discrete_params(self, discrete):
        return ()

    def continuous_params(self, discrete):
        return (
            ContinuousParam("l1", 0.15, 0.4),
            ContinuousParam("l2", 0.1, 0.35),
            ContinuousParam("radius", 0.01, 0.04),
        )

    def nominal(self):
        return Design(self.name, (), (0.28, 0.22, 0.02))

    def _mjcf(self, discrete, values, options):
        l1, l2, r = values["l1"], values["l2"], values["radius"]
        return f"""<mujoco model="planar_arm"><compiler angle="radian"/>
<option timestep="0.002" integrator="Euler"><flag contact="disable"/></option>
<worldbody><body name="b1" pos="0 0 0.1"><joint name="j1" type="hinge" axis="0 0 1" range="-3 3"/>
<geom type="capsule" fromto="0 0 0 {l1} 0 0" size="{r}" density="{DENSITY}"/>
<body name="b2" pos="{l1} 0 0" euler="0 0 1.5707963267948966">
<joint name="j2" type="hinge" axis="0 0 1" range="-2.8 2.8"/>
<geom type="capsule" fromto="0 0 0 {l2} 0 0" size="{r}" density="{DENSITY}"/><site name="ee_0" pos="{l2} 0 0"/>
</body></body>
</worldbody><actuator><position joint="j1" kp="30" kv="2" ctrlrange="-3 3"/>
<position joint="j2" kp="30" kv="2" ctrlrange="-2.8 2.8"/></actuator></mujoco>"""


def circle(steps: int = 25) -> Motion:
    t = np.arange(steps) * 0.02
    pos = np.stack([0.22 + 0.06 * np.cos(3 * t), 0.18 + 0.06 * np.sin(3 * t), np.full_like(t, 0.1)], -1)[:, None]
    yaw = np.pi / 2 + 0.3 * np.sin(3 * t)
    quat = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], -1)[:, None]
    return Motion("circle", pos, quat)


# ------------------------------------------------------------------------------ the boundary
@wp.kernel
def _scaled_norm(
    x: wp.array(dtype=wp.vec3), s: wp.array(dtype=float), y: wp.array(dtype=wp.vec3), big: wp.array(dtype=wp.int32)
):
    i = wp.tid()
    n = wp.length(x[i])
    y[i] = x[i] * (s[0] * n) + wp.vec3(wp.sin(x[i][0]), 0.0, 0.0)
    big[i] = wp.where(n > 1.0, 1, 0)


class ScaledNorm(WarpProgram):
    dtypes = (wp.vec3, float)

    def __init__(self):
        self.seen: list[int] = []
        self.outputs: list[wp.array] = []

    def record(self, arrays):
        x, s = arrays
        self.seen = [a.ptr for a in arrays]
        y = wp.zeros(x.shape, dtype=wp.vec3, device=x.device, requires_grad=True)
        big = wp.zeros(x.shape, dtype=wp.int32, device=x.device)
        wp.launch(_scaled_norm, dim=x.shape, inputs=[x, s], outputs=[y, big], device=x.device)
        self.outputs = [y, big]
        return self.outputs


def test_warp_function_matches_torch_autograd_without_copies():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(64, 3, generator=g).requires_grad_(True)
    s = torch.tensor([0.7]).requires_grad_(True)
    w = torch.randn(64, 3, generator=g)
    program = ScaledNorm()
    y, big = WarpFunction.apply(program, x, s)
    # Zero-copy both ways: Warp read the tensors' memory, torch reads Warp's outputs.
    assert program.seen == [x.data_ptr(), s.data_ptr()]
    assert y.data_ptr() == program.outputs[0].ptr and not big.requires_grad
    ((y * w).sum()).backward()
    xr, sr = x.detach().clone().requires_grad_(True), s.detach().clone().requires_grad_(True)
    yr = xr * (sr * xr.norm(dim=1, keepdim=True)) + torch.stack([torch.sin(xr[:, 0]), 0 * xr[:, 0], 0 * xr[:, 0]], 1)
    ((yr * w).sum()).backward()
    torch.testing.assert_close(y, yr.detach(), atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(x.grad, xr.grad, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(s.grad, sr.grad, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(big, (xr.detach().norm(dim=1) > 1).int())


# ------------------------------------------------------------------------------ design -> fields
def test_field_jacobian_matches_hand_derivatives():
    space = PlanarArm()
    design = space.nominal()
    l1, l2, r = design.continuous
    jac = field_jacobian(space, design, space.ee_sites()).jacobian  # (p=3, ...) per field
    # Body 2 sits at (l1, 0, 0) in body 1; the site at (l2, 0, 0) in body 2.
    np.testing.assert_allclose(jac["body_pos"][0, 2], [1, 0, 0], atol=2e-3)
    np.testing.assert_allclose(jac[("64", "body_pos")][0, 2], [1, 0, 0], atol=1e-7)
    np.testing.assert_allclose(jac["ee_pos"][1, 0], [1, 0, 0], atol=2e-3)
    np.testing.assert_allclose(jac["body_pos"][1:, 2], 0, atol=2e-3)
    # Body 1's centre of mass at l1 / 2 along x.
    np.testing.assert_allclose(jac["body_ipos"][0, 1], [0.5, 0, 0], atol=2e-3)
    # Capsule mass rho (pi r^2 l + 4/3 pi r^3): d/dl = rho pi r^2, d/dr = rho (2 pi r l + 4 pi r^2).
    np.testing.assert_allclose(jac["body_mass"][0, 1], DENSITY * math.pi * r**2, rtol=2e-3)
    np.testing.assert_allclose(jac["body_mass"][2, 1], DENSITY * (2 * math.pi * r * l1 + 4 * math.pi * r**2), rtol=2e-3)
    np.testing.assert_allclose(
        jac["mass"],
        DENSITY * np.array([math.pi * r**2, math.pi * r**2, 2 * math.pi * r * (l1 + l2) + 8 * math.pi * r**2]),
        rtol=2e-3,
    )
    # Size: each capsule's longest dimension is l + 2 r.
    np.testing.assert_allclose(jac["size"], [1, 1, 4], rtol=1e-6)


# ------------------------------------------------------------------------------ choices -> tokens
def test_choice_gradient_maps_to_tokens_through_the_linearised_decode():
    rng = np.random.default_rng(0)
    # Algebra: along any change the design can make (de = J dc), <g_e, de> = <g_c, dc>.
    J = {"a": rng.standard_normal((3, 4, 5)), "b": rng.standard_normal((3, 2, 2))}
    g_c = rng.standard_normal(3)
    g_e = tokens_from_choice_gradient(J, g_c)
    dc = rng.standard_normal(3)
    de = {n: np.tensordot(dc, J[n], axes=1) for n in J}
    assert sum(float((g_e[n] * de[n]).sum()) for n in J) == pytest.approx(float(g_c @ dc), rel=1e-10)
    # A real design space: every continuous choice moves the tokens (full rank), and the
    # linearised decode recovers a small perturbation of the choices from the tokens alone.
    space = get_space("viperx")
    discrete = space.sample(1, seed=5)[0].discrete
    params = space.continuous_params(discrete)
    # Away from the bounds (one-sided differences there are covered by the stencil, not here).
    design = Design(
        space.name,
        discrete,
        tuple(q.low + (0.3 + 0.4 * k / len(params)) * (q.high - q.low) for k, q in enumerate(params)),
    )
    jac = token_jacobian(space, design)
    p = len(design.continuous)
    flat = np.concatenate([jac[n].reshape(p, -1) for n in jac], 1).T  # (N, p)
    assert np.linalg.matrix_rank(flat, tol=1e-6) == p
    dc = 1e-3 * np.array([(q.high - q.low) * (1 if k % 2 else -1) for k, q in enumerate(params)])
    moved = Design(space.name, design.discrete, tuple(np.asarray(design.continuous) + dc))
    e0, e1 = encoded_tokens(space, [design, moved])
    de = np.concatenate([(e1[n] - e0[n]).ravel() for n in jac])
    recovered = np.linalg.pinv(flat) @ de
    np.testing.assert_allclose(recovered, dc, atol=2e-3 * np.abs(dc).max())


# ------------------------------------------------------------------------------ the whole chain
def test_simulated_reward_gradient_matches_finite_differences():
    space = PlanarArm()
    design = space.nominal()
    motion = circle()
    cfg = RewardConfig(
        name="tracking",
        space="viperx",
        torque_alpha=5e-5,
        velocity_alpha=0.1,
        size_alpha=0.1,
        size_target=0.3,
        mass_alpha=10.0,
        mass_target=0.5,
    )
    got = design_reward_gradient(space, [design], [motion], cfg, guidance=False, device="cpu")
    # The reward on the differentiable path is the oracle's (MuJoCo C + mink) reward.
    model = space.model(design)
    ep = oracle_rollout([model], [motion])
    oracle = evaluate(
        RewardInputs.from_episode(
            ep, robot_size([model], dtype=torch.float64), robot_mass([model], dtype=torch.float64)
        ),
        cfg,
    ).reward
    assert got.reward[0] == pytest.approx(float(oracle[0]), rel=1e-4)
    assert np.isfinite(got.grad[0]).all()
    c0 = np.asarray(design.continuous)
    fd = []
    for j, h in enumerate((1e-3, 1e-3, 2e-4)):
        r = []
        for sign in (1, -1):
            c = c0.copy()
            c[j] += sign * h
            moved = Design(space.name, (), tuple(c))
            value = design_reward_gradient(space, [moved], [motion], cfg, guidance=False, gradient=False, device="cpu")
            r.append(value.reward[0])
        fd.append((r[0] - r[1]) / (2 * h))
    fd = np.array(fd)
    # Each component on its own (they span 300 to 18000): 1e-2 relative.
    np.testing.assert_allclose(got.grad[0], fd, rtol=1e-2, atol=0.1)


def _token_gradient_case(monkeypatch=None):
    """A candidate whose tokens are the planar arm's nominal design, a small design change,
    and `SimGradient.token_gradient` at the candidate. With `monkeypatch`, the simulated
    reward is replaced by R(c) = -|c - c*|^2 (no rollout). Returns (<grad, dx>, dR) for the
    central differences dx = (x(c + dc) - x(c - dc)) / 2 and dR = (R(c + dc) - R(c - dc)) / 2
    (both exact to second order)."""
    import warnings
    from types import SimpleNamespace

    from tt.dit.layout import layout_from_schema
    from tt.guidance import simgrad
    from tt.guidance.predicted import build_query
    from tt.guidance.zeroth import Decoded
    from tt.tokens.batch import TokenBatch
    from tt.tokens.normalize import Normalizer
    from tt.tokens.tokenize import tokenize_models

    space = PlanarArm()
    design = space.nominal()
    dc = np.array([2e-3, -1.5e-3, 3e-4])
    plus = Design(space.name, (), tuple(np.asarray(design.continuous) + dc))
    minus = Design(space.name, (), tuple(np.asarray(design.continuous) - dc))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        emb = tokenize_models([space.model(d) for d in (design, plus, minus)]).tokens
    motion = circle()
    mats = np.stack([np.eye(3)] * motion.steps)  # target rotations only need a range here
    poses = np.concatenate([motion.pos[:, 0], mats.reshape(-1, 9)], -1)[None].astype(np.float32)
    targets = TokenBatch(
        {"target_pose": poses},
        {"target_pose": np.zeros((1, motion.steps, 2), np.int64)},
        {"target_pose": np.ones((1, motion.steps), bool)},
    )
    norm = Normalizer.fit([emb, targets])
    counts = {n: int(np.asarray(emb.mask[n]).sum(1).max()) + 2 for n in emb.types}  # room for padding
    layout = layout_from_schema({**counts, "track_link_obs": 1, "target_pose": 1}, steps=8)
    padded = norm.normalize(emb.pad_to({n: counts[n] for n in emb.types}).to_torch())
    x = {n: padded.values[n][:1].clone() for n in emb.types}
    dx = {n: (padded.values[n][1:2] - padded.values[n][2:3]).double() / 2 for n in emb.types}
    cfg = RewardConfig(
        name="tracking",
        space="viperx",
        torque_alpha=5e-5,
        velocity_alpha=0.1,
        size_alpha_guidance=0.1,
        size_target=0.3,
        mass_alpha_guidance=10.0,
        mass_target=0.5,
    )
    if monkeypatch is not None:
        c_star = np.array([0.3, 0.15, 0.03])

        def quadratic(space, designs, motions, cfg, *, gradient=True, **kw):
            c = np.array([d.continuous for d in designs])
            return simgrad.DesignGradient(-((c - c_star) ** 2).sum(1), list(-2 * (c - c_star)), 0)

        monkeypatch.setattr(simgrad, "design_reward_gradient", quadratic)
    ctx = SimpleNamespace(queries=[build_query(layout, norm, motion, 1)], motions=(motion,))
    sim = simgrad.SimGradient(
        space,
        cfg,
        SimpleNamespace(layout=layout, normalizer=norm),
        decoder=lambda batch, i: Decoded(design, None, 0.0),
        device="cpu",
    )
    grad = sim.token_gradient(ctx, x, step=0)
    assert sim.summary()["candidates"] == 1 and sim.summary()["decode_failures"] == 0
    # Padding slots get no gradient.
    for n, g in grad.items():
        assert bool((g[0, ~padded.mask[n][0]] == 0).all()), n
    predicted = sum(float((grad[n].double() * dx[n]).sum()) for n in grad)
    r = simgrad.design_reward_gradient(
        space, [plus, minus], [motion], cfg, guidance=True, gradient=False, device="cpu"
    ).reward
    return predicted, (r[0] - r[1]) / 2


def test_token_space_gradient_predicts_a_reward_change(monkeypatch):
    """Choices -> tokens -> normalised slots, without the rollout: <grad, dx> along the
    tokens of a design change is the reward change. Tolerance: float32 tokens (the change is
    ~1e-3 of the range) and the tokens' curvature in c (central differences: third order)."""
    predicted, actual = _token_gradient_case(monkeypatch)
    assert predicted == pytest.approx(actual, rel=2e-3)


def test_token_space_gradient_predicts_the_simulated_reward_change():
    """The same with the simulated reward (differentiable Warp rollout)."""
    predicted, actual = _token_gradient_case()
    assert predicted == pytest.approx(actual, rel=1e-2)
