"""Gravity compensation (MuJoCo's body ``gravcomp``) in tt's Warp kernels against MuJoCo C, and
the ``<space>-gravcomp`` variants (`tt.sim.designs.gravcomp`) the paper's evaluation uses.

The checks and tolerances are those of the uncompensated arms:

* one physics step from random states, limits active in some (`test_kernels_dynamics`):
  h * qacc within 1e-4 of the largest acceleration, on random viperx-gravcomp designs and on
  a hand-written tree with slide joints, a two-joint body, partial and negative gravcomp
  and a tilted gravity;
* 2 s of open-loop control on random viperx-gravcomp designs: each design within 1e-3 rad
  or 10x MuJoCo's own sensitivity to a 1e-6 rad start perturbation, the median below 1e-4;
* closed loop against the oracle (MuJoCo C + mink, `test_rollout._compare`): same survival,
  mean position error within 0.2 cm, tracking reward within 2 % on the reproducible episodes.

Plus the space variants' MJCF (round trip through MuJoCo's XML writer and ``tt designs``
files, fast tree path equal to MuJoCo's compile) and the refusals that remain.
"""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest
import warp as wp
from test_kernels_dynamics import HORIZON_STEPS, HORIZON_TOL, MEDIAN_TOL, STEP_REL_TOL, _ctrl_sequence, _mujoco_run

from tt.kernels.dynamics import simulate
from tt.kernels.errors import TTError
from tt.kernels.model import FIELD_NAMES, build_tree_model, topology_key, tree_fields
from tt.sim.designs import DesignError, get_space, load_designs
from tt.sim.designs.gravcomp import GRAVCOMP_BASES, GravcompSpace, add_gravcomp, gravcomp_name

SPACE = "viperx-gravcomp"

#: A tree no tt space builds: slide joints, a body with two joints (split into a chain of
#: tree bodies), gravcomp 0, partial, full, over-full and negative, gravity not along -z.
TREE_XML = """<mujoco>
  <option timestep="0.002" integrator="Euler" gravity="1.5 -0.7 -9.6">{flags}</option>
  <default><geom contype="0" conaffinity="0" density="800"/></default>
  <worldbody>
    <body name="a" pos="0 0 0.1" gravcomp="{g0}">
      <joint name="j0" type="slide" axis="0 0.6 0.8" range="-0.2 0.2" damping="2"/>
      <geom type="box" size="0.05 0.04 0.03"/>
      <body name="b" pos="0.05 0 0.1" quat="0.9 0.1 0.3 0" gravcomp="{g1}">
        <joint name="j1" axis="0 1 0" pos="0 0 -0.02" range="-1.5 1.5" damping="1" stiffness="3"/>
        <joint name="j2" axis="1 0 0.3" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0.05" size="0.02"/>
        <body name="c" pos="0.25 0 0.05" gravcomp="{g2}">
          <joint name="j3" axis="0 0.2 1" range="-2 2" armature="0.01"/>
          <geom type="capsule" fromto="0 0 0 0 0.2 0.1" size="0.015"/>
          <body name="d" pos="0 0.2 0.1" gravcomp="{g3}">
            <joint name="j4" type="slide" axis="1 0 0" range="-0.05 0.05" damping="0.5"/>
            <geom type="sphere" size="0.03"/>
            <site name="ee_0"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position joint="j0" kp="300" kv="10" ctrlrange="-0.2 0.2" forcerange="-40 40"/>
    <position joint="j1" kp="30" ctrlrange="-1.5 1.5" forcerange="-4 4"/>
    <position joint="j2" kp="20" kv="1" ctrlrange="-1 1"/>
    <position joint="j3" kp="10" ctrlrange="-2 2" forcerange="-2 2"/>
  </actuator>
</mujoco>"""


def _tree(gravcomp=(0.0, 0.3, 1.0, -0.5), flags="") -> mujoco.MjModel:
    g0, g1, g2, g3 = gravcomp
    return mujoco.MjModel.from_xml_string(TREE_XML.format(g0=g0, g1=g1, g2=g2, g3=g3, flags=flags))


def _one_step(models, sites, rng, device):
    """qacc of one step from random states (some joints past a limit) by warp and MuJoCo,
    and MuJoCo's qfrc_gravcomp, (W, NV) each."""
    W, nv = len(models), models[0].nv
    q, qd, ctrl = np.zeros((W, nv)), rng.normal(0.0, 1.0, (W, nv)), np.zeros((W, 1, models[0].nu))
    qd_next, gravcomp = np.zeros((W, nv)), np.zeros((W, nv))
    for i, m in enumerate(models):
        lo, hi = m.jnt_range.T
        q[i] = rng.uniform(lo - 0.05, hi + 0.05)
        ctrl[i, 0] = rng.uniform(*m.actuator_ctrlrange.T)
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:], d.ctrl[:] = q[i], qd[i], ctrl[i, 0]
        mujoco.mj_forward(m, d)
        gravcomp[i] = d.qfrc_gravcomp
        mujoco.mj_step(m, d)
        qd_next[i] = d.qvel
    tree = build_tree_model(models, sites, device=device)
    f32 = lambda x: wp.array(np.asarray(x, np.float32), dtype=float, device=device)  # noqa: E731
    out = simulate(tree, f32(q), f32(qd), f32(ctrl))
    h = models[0].opt.timestep
    return (out.qvel.numpy()[:, 1] - qd.astype(np.float32)) / h, (qd_next - qd) / h, gravcomp


def _assert_step_close(acc_warp, acc_ref):
    scale = np.abs(acc_ref).max(axis=1, keepdims=True)
    assert np.all(np.abs(acc_warp - acc_ref) <= STEP_REL_TOL * scale), np.abs(acc_warp - acc_ref).max()


def test_one_step_matches_mujoco_on_viperx_gravcomp_designs(device):
    space = get_space(SPACE)
    rng = np.random.default_rng(0)
    groups: dict[tuple, list] = {}
    for design in space.sample(40, seed=2):
        m = space.model(design)
        groups.setdefault(topology_key(m, space.ee_sites()), []).append(m)
    compensated = 0.0
    for models in groups.values():
        acc_warp, acc_ref, gravcomp = _one_step(models, space.ee_sites(), rng, device)
        _assert_step_close(acc_warp, acc_ref)
        compensated = max(compensated, float(np.abs(gravcomp).max()))
    assert compensated > 1.0  # [N m]: the compensation is a real share of the forces


@pytest.mark.parametrize(
    "gravcomp, flags",
    [
        ((0.0, 0.3, 1.0, -0.5), ""),
        ((1.0, 1.0, 1.0, 1.0), ""),
        ((2.0, 0.0, 0.7, 1.0), '<flag spring="disable"/>'),
        ((1.0, 1.0, 1.0, 1.0), '<flag spring="disable" damper="disable"/>'),  # MuJoCo skips it
        ((1.0, 1.0, 1.0, 1.0), '<flag gravity="disable"/>'),
    ],
)
def test_one_step_matches_mujoco_on_a_general_tree(gravcomp, flags, device):
    """MuJoCo's semantics on what tt's spaces do not build: slide joints, a two-joint body,
    per-body shares (negative and above one too), tilted gravity, and the flags that turn
    the compensation off."""
    rng = np.random.default_rng(3)
    models = [_tree(gravcomp, flags) for _ in range(12)]
    acc_warp, acc_ref, qfrc = _one_step(models, ("ee_0",), rng, device)
    _assert_step_close(acc_warp, acc_ref)
    fields = tree_fields(models[:1], ("ee_0",))
    off = "gravity" in flags or "damper" in flags
    assert (np.abs(fields.values["body_gravcomp"]).max() == 0.0) == off
    assert (np.abs(qfrc).max() == 0.0) == off


def test_two_seconds_open_loop_on_viperx_gravcomp_designs(device):
    space = get_space(SPACE)
    rng = np.random.default_rng(1)
    errors, sensitivity = [], []
    groups: dict[tuple, list] = {}
    for design in space.sample(48, seed=5):
        m = space.model(design)
        groups.setdefault(topology_key(m, space.ee_sites()), []).append(m)
    for models in groups.values():
        ctrl = _ctrl_sequence(models, HORIZON_STEPS, rng)
        qpos0 = np.stack([m.qpos0 for m in models]).astype(np.float32)
        tree = build_tree_model(models, space.ee_sites(), device=device)
        out = simulate(tree, *(wp.array(a, dtype=float, device=device) for a in (qpos0, np.zeros_like(qpos0), ctrl)))
        for i, m in enumerate(models):
            ref, _ = _mujoco_run(m, qpos0[i], ctrl[i])
            perturbed, _ = _mujoco_run(m, qpos0[i] + 1e-6 * rng.standard_normal(m.nq), ctrl[i])
            errors.append(np.abs(out.qpos.numpy()[i] - ref).max())
            sensitivity.append(np.abs(perturbed - ref).max())
    errors, sensitivity = np.array(errors), np.array(sensitivity)
    assert len(errors) == 48
    assert np.median(errors) < MEDIAN_TOL
    assert np.all(errors <= np.maximum(HORIZON_TOL, 10.0 * sensitivity)), (errors.max(), sensitivity[errors.argmax()])


def test_warp_matches_the_oracle_with_gravcomp(device):
    """Closed loop, warp against the oracle on the same compensated designs, with the
    tolerances of `test_rollout`; and the compensation changes the episodes."""
    from test_rollout import _compare

    from tt.sim.motions import motion_set

    space = get_space(SPACE)
    designs = space.sample(16, seed=11)
    motions = motion_set("train", arms=1)[:2]
    warp_ep, oracle_ep = _compare(SPACE, designs, motions, min_reproducible=0.75, device=device)
    from tt.sim.rollout import rollout

    plain = rollout([space.to_base(d) for d in designs], motions, backend="mujoco")
    assert float((plain.qpos - oracle_ep.qpos).abs().max()) > 1e-3


def test_trees_match_mujoco_compile_with_gravcomp():
    """The fast tree path (`DesignSpace.trees`) of the variant equals `tree_fields` of its
    compiled MJCF field by field, body_gravcomp included."""
    sp = get_space(SPACE)
    designs = sp.sample(40, seed=11)
    trees = sp.trees(designs)
    assert trees.space == SPACE
    for members, fields in trees.groups:
        models = [sp.model(designs[i]) for i in members]
        ref = tree_fields(models, sp.ee_sites())
        assert fields.topology == ref.topology
        np.testing.assert_array_equal(ref.values["body_gravcomp"][:, 1:], 1.0)
        for name in FIELD_NAMES:
            if name in ("body_iquat", "body_inertia"):  # principal frames: not unique
                continue
            np.testing.assert_allclose(fields.values[name], ref.values[name], rtol=1e-12, atol=1e-12, err_msg=name)


def test_mjcf_round_trip_keeps_gravcomp(tmp_path, tt_cli):
    """A variant's MJCF has gravcomp on every body and actuatorgravcomp on every joint, as
    the paper's detokenizer writes it; MuJoCo's XML writer keeps both, and so do the files
    ``tt designs`` writes (MJCF and designs.json)."""
    for base in GRAVCOMP_BASES:
        sp = get_space(gravcomp_name(base))
        design = sp.sample(1, seed=4)[0]
        m = sp.model(design)
        assert np.all(m.body_gravcomp[1:] == 1.0) and np.all(m.jnt_actgravcomp)
        plain = get_space(base).model(sp.to_base(design))
        assert np.all(plain.body_gravcomp == 0.0)
        # Everything else is the base space's robot.
        for name in ("body_mass", "body_pos", "jnt_axis", "actuator_gainprm", "actuator_forcerange"):
            np.testing.assert_array_equal(getattr(m, name), getattr(plain, name), err_msg=name)
        spec = mujoco.MjSpec.from_string(sp.to_mjcf(design))
        spec.compile()
        again = mujoco.MjModel.from_xml_string(spec.to_xml())  # MuJoCo's own MJCF writer
        np.testing.assert_array_equal(again.body_gravcomp, m.body_gravcomp)
        np.testing.assert_array_equal(again.jnt_actgravcomp, m.jnt_actgravcomp)
    code, out = tt_cli(["designs", "--space", SPACE, "--n", "2", "--seed", "0", "--out", str(tmp_path / "d")])
    assert code == 0, out
    record = json.loads((tmp_path / "d" / "designs.json").read_text())
    assert [d["space"] for d in record["designs"]] == [SPACE, SPACE]
    assert [d.space for d in load_designs(tmp_path / "d" / "designs.json")] == [SPACE, SPACE]
    for name in record["files"]:
        m = mujoco.MjModel.from_xml_path(str(tmp_path / "d" / name))
        assert np.all(m.body_gravcomp[1:] == 1.0)
        assert np.all(tree_fields([m], ("ee_0",)).values["body_gravcomp"][0, 1:] == 1.0)


def test_keyword_and_names():
    assert get_space("viperx", gravcomp=True) is get_space(SPACE)
    assert get_space(SPACE, gravcomp=True) is get_space(SPACE)
    sp = get_space("viperx-nominal", gravcomp=True)
    assert isinstance(sp, GravcompSpace) and sp.family == "viperx" and sp.nominal().space == sp.name
    design = get_space("viperx").sample(1, seed=0)[0]
    assert get_space(SPACE).from_base(design).space == SPACE
    for name in ("quadruped", "bimanual"):
        with pytest.raises(DesignError, match="no gravity-compensated variant"):
            get_space(name, gravcomp=True)
    with pytest.raises(DesignError, match="already sets gravcomp"):
        add_gravcomp(get_space(SPACE).to_mjcf(get_space(SPACE).nominal()))


def test_what_stays_refused():
    """Newton does not replicate gravity compensation; the tree kernels refuse MuJoCo's one
    case they do not replicate (compensation booked as actuation, with actuation disabled)."""
    from tt.sim.newton_backend import _check_newton_model

    m = get_space(SPACE).model(get_space(SPACE).nominal())
    with pytest.raises(TTError, match="body_gravcomp is nonzero; gravity compensation is not replicated on Newton"):
        _check_newton_model(m, 0)
    _check_newton_model(get_space("viperx").model(get_space("viperx").nominal()), 0)
    off = mujoco.MjModel.from_xml_string(
        get_space(SPACE)
        .to_mjcf(get_space(SPACE).nominal())
        .replace('<flag contact="disable"/>', '<flag contact="disable" actuation="disable"/>')
    )
    with pytest.raises(TTError, match="actuatorgravcomp"):
        tree_fields([off], ("ee_0",))


@pytest.mark.slow
def test_rollout_gradients_with_gravcomp_match_float64_finite_differences():
    """`wp.Tape` gradients through the differentiable rollout of a compensated arm equal
    float64 finite differences of the oracle's, as `test_kernels_rollout` checks them
    without compensation (link offsets and mount yaw, relative 1e-2)."""
    from test_kernels_rollout import _check_design_gradients

    from tt.sim.controller import IKConfig
    from tt.sim.motions import motion_set

    space = get_space(SPACE)
    _check_design_gradients(space, space.nominal(), motion_set("train", arms=1)[0], IKConfig())
