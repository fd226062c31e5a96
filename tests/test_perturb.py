"""Control perturbation of the warp rollout (`rollout(..., action_noise=sigma, noise_seed=s)`).

The paper's data generation executes noisy commands and logs the clean ones. Checked here:
* sigma = 0 is the unperturbed rollout bit for bit, whatever the seed (the unperturbed
  rollout itself is checked against the oracle in tests/test_rollout.py);
* with noise, the actuators execute clip(action + sigma n, ctrlrange): one control step
  replayed from the recorded state in MuJoCo C with the recorded ``ctrl`` lands on the
  recorded next state, with the clean ``action`` it does not; n is the stream of
  `action_noise_draws`, standard normal (Kolmogorov-Smirnov), uncorrelated across steps;
* the logged ``action`` is the clean DiffIK command at the perturbed state: recomputed from
  the recorded states by mink (the oracle's controller, float64) within the IK kernels'
  tolerance against it;
* the same seed gives identical episodes whatever the chunking, another seed other noise.
Designs: the nominal ViperX (6 DoF) and a 7- and a 5-DoF design (three topology groups, so
the zero-padded multi-group Episode is covered); motions cut to 40 steps.
"""

from dataclasses import fields

import mujoco
import numpy as np
import pytest
import torch
import warp as wp
from scipy import stats

from tt.kernels.rollout import action_noise_draws
from tt.sim.controller import DiffIKController, IKConfig, actuated_qpos
from tt.sim.designs import get_space
from tt.sim.motions import for_space, motion_set
from tt.sim.motions.base import Motion
from tt.sim.rollout import rollout

STEPS = 40
SIGMA = 0.05  # [rad]: large enough that one step's replay tells the noisy command from the clean one
IK_TOL = 1e-3  # [rad], tt.kernels.ik against mink (tests/test_kernels_ik.py)
REPLAY_TOL = 1e-5  # [rad], one control step (10 physics steps) of float32 kernels against MuJoCo C


@pytest.fixture(scope="module")
def case():
    space = get_space("viperx")
    nominal = space.nominal()
    # The first 7-DoF and the first 5-DoF design of this sample (both track the cut motions).
    sample = space.sample(40, seed=5)
    others = [next(d for d in sample if space.model(d).nv == nv) for nv in (7, 5)]
    designs = [nominal, *others]
    motions = for_space(motion_set("train", arms=1)[:2], "viperx")
    motions = [Motion(m.name, m.pos[:STEPS], m.quat[:STEPS], m.dt) for m in motions]
    clean = rollout(designs, motions, device="cpu")
    noisy = rollout(designs, motions, device="cpu", action_noise=SIGMA, noise_seed=7)
    return space, designs, motions, clean, noisy


def _tensors(ep):
    return {f.name: getattr(ep, f.name) for f in fields(ep) if isinstance(getattr(ep, f.name), torch.Tensor)}


def _assert_same(a, b):
    for name, x in _tensors(a).items():
        y = getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y), name


def test_zero_noise_is_the_unperturbed_rollout_bit_for_bit(case):
    space, designs, motions, clean, _ = case
    assert clean.action is clean.ctrl  # no perturbation: the executed command is the logged one
    # Whatever the seed: sigma = 0 never draws.
    _assert_same(rollout(designs, motions, device="cpu", action_noise=0.0, noise_seed=123), clean)


def test_the_actuators_execute_the_noisy_command(case):
    space, designs, motions, clean, noisy = case
    M = len(motions)
    alive = noisy.alive
    executed = (noisy.qpos - clean.qpos)[alive & clean.alive].abs().amax()
    assert executed > 1e-3, executed  # the perturbation changes the trajectory
    draws = action_noise_draws(7, np.arange(noisy.worlds), STEPS, noisy.ctrl.shape[-1])
    replays, cleans = [], []
    for w in range(noisy.worlds):
        model = space.model(designs[w // M])
        nu, n = model.nu, int(noisy.lengths()[w])
        lo, hi = model.actuator_ctrlrange.T.astype(np.float32)
        action = noisy.action[w, :n, :nu].numpy()
        expected = np.clip(action + np.float32(SIGMA) * draws[w, :n, :nu], lo, hi)
        # float32 either way; the kernel may fuse the multiply-add (one rounding fewer).
        np.testing.assert_allclose(noisy.ctrl[w, :n, :nu].numpy(), expected, rtol=0, atol=1e-6)
        assert (noisy.ctrl[w, n:] == noisy.ctrl[w, n - 1]).all()  # repeated after termination
        assert (noisy.action[w, n:] == noisy.action[w, n - 1]).all()
        # One control step in MuJoCo C from the recorded state, with either command.
        substeps = round(IKConfig().control_dt / model.opt.timestep)
        for t in (1, n // 2, n - 1):
            data = mujoco.MjData(model)

            def step(command):
                data.qpos[:] = noisy.qpos[w, t - 1, : model.nq].numpy()
                data.qvel[:] = noisy.qvel[w, t - 1, : model.nv].numpy()
                data.ctrl[:] = command
                for _ in range(substeps):
                    mujoco.mj_step(model, data)
                return np.abs(data.qpos - noisy.qpos[w, t, : model.nq].numpy()).max()

            replays.append(step(noisy.ctrl[w, t, :nu].numpy()))
            cleans.append(step(noisy.action[w, t, :nu].numpy()))
    replays, cleans = np.array(replays), np.array(cleans)
    assert len(replays) == 3 * noisy.worlds
    assert replays.max() <= REPLAY_TOL, replays.max()
    assert np.median(cleans) > 10 * REPLAY_TOL, np.median(cleans)


def test_logged_action_is_the_clean_ik_command_at_the_perturbed_state(case):
    space, designs, motions, _, noisy = case
    config = IKConfig()
    M = len(motions)
    checked = 0
    for w in range(noisy.worlds):
        model = space.model(designs[w // M])
        controller = DiffIKController(model, config)
        motion = motions[w % M]
        adr = actuated_qpos(model)
        lo, hi = model.actuator_ctrlrange.T
        n = int(noisy.lengths()[w])
        for t in range(1, n, 6):
            goal = min(t + config.lookahead_steps, motion.steps - 1)
            q = noisy.qpos[w, t - 1, : model.nq].numpy().astype(np.float64)
            ref = np.clip(controller.step(q, motion.pos[goal], motion.quat[goal])[adr], lo, hi)
            np.testing.assert_allclose(noisy.action[w, t, : model.nu].numpy(), ref, rtol=0, atol=IK_TOL)
            checked += 1
    assert checked >= 30


def test_noise_draws_are_standard_normal_and_independent():
    n = action_noise_draws(11, np.arange(64), 200, 6)  # (W, T, NU)
    assert n.shape == (64, 200, 6) and n.dtype == np.float32
    flat = n.ravel().astype(np.float64)
    assert stats.kstest(flat, "norm").pvalue > 1e-3
    assert abs(flat.mean()) < 4 / np.sqrt(flat.size) and abs(flat.std() - 1) < 0.01
    lag = np.corrcoef(n[:, 1:].ravel(), n[:, :-1].ravel())[0, 1]
    worlds = np.corrcoef(n[1:].ravel(), n[:-1].ravel())[0, 1]
    actuators = np.corrcoef(n[..., 1:].ravel(), n[..., :-1].ravel())[0, 1]
    assert max(abs(lag), abs(worlds), abs(actuators)) < 4 / np.sqrt(flat.size / 2)
    # A window of steps and a subset of worlds draw the same values (keyed by world id and step).
    np.testing.assert_array_equal(action_noise_draws(11, [5, 9], 20, 6, t_begin=30), n[[5, 9], 30:50])


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device")
def test_noise_draws_agree_across_devices():
    # Same integer stream; log and cos are float32 library calls (an ulp or two apart).
    cpu = action_noise_draws(3, np.arange(256), 100, 7, device="cpu")
    cuda = action_noise_draws(3, np.arange(256), 100, 7, device="cuda")
    np.testing.assert_allclose(cuda, cpu, rtol=1e-5, atol=1e-6)


def test_same_seed_same_episodes_whatever_the_chunking(case):
    space, designs, motions, _, noisy = case
    _assert_same(rollout(designs, motions, device="cpu", action_noise=SIGMA, noise_seed=7, chunk=7), noisy)
    other = rollout(designs, motions, device="cpu", action_noise=SIGMA, noise_seed=8)
    assert not torch.equal(other.ctrl, noisy.ctrl) and not torch.equal(other.qpos, noisy.qpos)


def test_bad_noise_arguments_are_refused(case):
    space, designs, motions, _, _ = case
    with pytest.raises(ValueError, match="action_noise = -0.1"):
        rollout(designs[:1], motions[:1], device="cpu", action_noise=-0.1)
    with pytest.raises(ValueError, match="noise_seed"):
        rollout(designs[:1], motions[:1], device="cpu", action_noise=0.1, noise_seed=2**31)
    with pytest.raises(ValueError, match="needs backend 'warp'"):
        rollout(designs[:1], motions[:1], backend="mujoco", action_noise=0.1)
