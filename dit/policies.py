"""Batched policies for the closed loop (`tt.dit.closed_loop`): the DiT controller and its reference.

* `ModelPolicy`: the trained DiT's control task (`tt.dit.tasks`), batched over the worlds
  still running: by default one network call per control step (the model's mean command;
  the paper samples 5 DDIM steps), each executed command the mean of what the recent queries
  predicted for its step (`ControllerConfig`); `model_rollout` runs it from a checkpoint.
* `IKPolicy`: the oracle's DiffIK with look-ahead (`tt.kernels.ik`), the reference the
  model is compared with; with it the loop reproduces the "warp" backend's rollout.

What the model is given at control step k, mirroring training. In the data, the record
of step j holds the state *after* the physics of step j and the command of step j, and
the DiffIK command of step j + 1 is computed from the state of record j and the target
at j + 1 + `IKConfig.lookahead_steps` (2 at 50 Hz). A control-task training window starts at a step j and holds:
the embodiment tokens (clean), the dynamics tokens of record j (clean: the "current
state"), the target poses of steps j .. j + 7 (clean) and, diffused, the commands of
steps j .. j + 7 and the states of records j + 1 .. j + 7. At control step k >= 1 the
measured state is record k - 1, so the query is the window starting at j = k - 1 (time
IDs k - 1 .. k + 6), and the command executed is the predicted command of the window's
second step, step k: the one that followed from that state in the data. A model trained with
``control_target_offset`` L is given the targets of steps j + L .. j + 7 + L instead, as in
training (`tt.dit.tasks.look_ahead`). At k = 0 there
is no record yet: the start posture at rest (with the command that holds it) stands in
for record 0 and the window's first command is executed. Targets past the motion's end
repeat its last pose, as the DiffIK's look-ahead does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from tt.dit.checkpoint import TrainedModel, load_checkpoint, load_model
from tt.dit.closed_loop import LoopContext, StepState, closed_loop_rollout
from tt.dit.layout import Layout, LayoutError
from tt.dit.sampling import sample
from tt.dit.tasks import CONTROL, TaskSpec
from tt.kernels.errors import TTError
from tt.sim.controller import IKConfig
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import STEP_ROLES

#: Controllers of `tt validate --controller`.
CONTROLLERS = ("ik", "model")


class IKPolicy:
    """The oracle's controller as a policy: one DiffIK step (`tt.kernels.ik.ik_step`, mink's
    problem in float32) toward the motion pose ``min(k + lookahead, T_m - 1)``, the command
    of each actuated joint. With it `closed_loop_rollout` reproduces the "warp" backend."""

    def reset(self, ctx: LoopContext) -> None:
        self.ctx = ctx
        dev = ctx.target_pos.device
        self._act = [
            torch.as_tensor(g.tree.topology.actuator_dof, dtype=torch.long, device=dev) for g in ctx.worlds.groups
        ]

    def __call__(self, step: int, worlds: torch.Tensor, state: StepState) -> torch.Tensor:
        import warp as wp

        from tt.kernels.ik import ik_step

        ctx = self.ctx
        sim = ctx.worlds
        goal = min(step + ctx.config.lookahead_steps, ctx.target_pos.shape[1] - 1)
        ctrl = torch.zeros(ctx.world_count, sim.nu, device=state.qpos.device)
        for g, act in zip(sim.groups, self._act):
            q = wp.from_torch(state.qpos[g.worlds, : g.nv].contiguous())
            tpos = wp.from_torch(ctx.target_pos[g.worlds, goal].contiguous(), dtype=wp.vec3)
            tquat = wp.from_torch(ctx.target_quat[g.worlds, goal].contiguous(), dtype=wp.vec4)
            q_cmd = wp.to_torch(ik_step(g.tree, q, tpos, tquat, ctx.config.ik_weights(), device=sim.device))
            ctrl[g.worlds, : g.nu] = q_cmd[:, act]
        return ctrl[worlds]


class HoldPolicy:
    """A still arm: every step repeats the last command (the start posture's), which is what
    a controller that learned no increment does; the floor a learned controller must clear."""

    def reset(self, ctx: LoopContext) -> None:
        pass

    def __call__(self, step: int, worlds: torch.Tensor, state: StepState) -> torch.Tensor:
        return state.ctrl[worlds].clone()


@dataclass(frozen=True)
class ControllerConfig:
    """How the model controls. num_steps: DDIM steps per control step (the paper's: 5, all
    of the control process's); eta: DDIM noise (0: deterministic given the seed); seed: of
    the initial noise of every query (one generator for the whole run); spacing: of the DDIM
    steps (`tt.dit.ddim.SPACINGS`; "trailing" with num_steps 1 executes one network call
    from pure noise at the noisiest level: the model's estimate of the mean command, not a
    sample of its distribution); ensemble: how many recent queries' chunks the executed
    command averages (temporal ensembling, Zhao et al. 2023: every query predicts the
    commands of its whole window, so step k's command was also predicted by the queries of
    steps k - 1, k - 2, ...; 1: the current query's alone, the paper's; None: every query
    whose window still holds the step, S - 1 for an S-step window); ensemble_decay: the
    weight of a prediction made a steps ago is exp(-ensemble_decay * a) (negative: older
    predictions weigh more, as in ACT).

    The defaults are what measured best on ViperX (25 held-out designs x 5 validation motions,
    whole motions; `benchmarks/results/dit_control_viperx_ensemble*.md`,
    `dit_control_r1_ensemble.md`): the shipped checkpoint reaches 8.1 % of the oracle's reward
    with the paper's 5 sampled steps and one query per command, 27.5 % with 7 queries
    averaged, 18.9 % with the mean command alone and 35.5 % with both, in a fifth of the
    network calls; on one structure (R1) the mean command scores as sampling does (21.8 /
    21.9 %) and averaging lifts it to 31.9 %."""

    num_steps: int = 1
    eta: float = 0.0
    seed: int = 0
    spacing: str = "trailing"
    ensemble: int | None = None
    ensemble_decay: float = 0.0

    def __post_init__(self) -> None:
        from tt.dit.ddim import SPACINGS

        if self.num_steps < 1:
            raise TTError(f"ControllerConfig.num_steps = {self.num_steps}; must be >= 1")
        if not self.eta >= 0:
            raise TTError(f"ControllerConfig.eta = {self.eta}; must be >= 0")
        if self.spacing not in SPACINGS:
            raise TTError(f"ControllerConfig.spacing = {self.spacing!r}; valid: {list(SPACINGS)}")
        if self.ensemble is not None and self.ensemble < 1:
            raise TTError(f"ControllerConfig.ensemble = {self.ensemble}; must be >= 1")
        if not math.isfinite(self.ensemble_decay):
            raise TTError(f"ControllerConfig.ensemble_decay = {self.ensemble_decay}; must be finite")


def control_task(checkpoint: str | Path) -> TaskSpec:
    """The control task a checkpoint was trained on (its diffusion steps and whether it
    diffused the future states), `tt.dit.tasks.CONTROL` when the checkpoint does not say."""
    from tt.dit.checkpoint import checkpoint_file

    path = checkpoint_file(checkpoint)
    return control_task_of(load_checkpoint(path).get("train_config"), f"checkpoint {path}")


def control_task_of(config: dict | None, where: str = "the checkpoint") -> TaskSpec:
    """`control_task` of a loaded checkpoint's train config (a dict, or None when it has none)."""
    cfg = config or {}
    if cfg.get("task", "control") == "robot":
        raise TTError(f"{where} was trained on the robot task only; the controller needs task control or both")
    return TaskSpec(
        "control",
        int(cfg.get("control_diffusion_steps", CONTROL.diffusion_steps)),
        "consecutive",
        bool(cfg.get("future_states", CONTROL.future_states)),
        bool(cfg.get("known_command", False)),
        int(cfg.get("control_target_offset", 0)),
    )


class ModelPolicy:
    """The DiT's control task as a batched policy (see the module docstring for the query).

    trained: the model (EMA weights), its normaliser and layout; task: the control task it
    was trained on (`control_task`); config: `ControllerConfig`.
    """

    def __init__(
        self, trained: TrainedModel, *, task: TaskSpec = CONTROL, config: ControllerConfig = ControllerConfig()
    ):
        if task.name != "control":
            raise TTError(f"ModelPolicy runs the control task, got task {task.name!r}")
        if config.num_steps > task.diffusion_steps:
            raise TTError(
                f"ControllerConfig.num_steps = {config.num_steps}; the control process has {task.diffusion_steps} steps"
            )
        layout = trained.layout
        need = {"control", "target_pose"}
        missing = sorted(need - set(layout.names))
        if missing:
            raise LayoutError(
                f"the model's layout lacks {missing}; the controller needs control and target_pose tokens"
            )
        self.trained = trained
        self.task = task
        self.config = config
        self.layout: Layout = layout
        # A query at step k' (window start k' - 1) predicts steps up to k' + S - 2.
        self.ensemble = layout.steps - 1 if config.ensemble is None else config.ensemble
        if self.ensemble > layout.steps - 1:
            raise TTError(
                f"ControllerConfig.ensemble = {config.ensemble}; the model's {layout.steps}-step window "
                f"predicts a step at most {layout.steps - 1} queries ahead"
            )
        self.model = trained.model.eval()
        self.device = next(self.model.parameters()).device

    def reset(self, ctx: LoopContext) -> None:
        """Tokenize the designs (embodiment tokens, padded to the layout) and index their actuators."""
        from tt.dit.layout import robot_embodiment

        self.ctx = ctx
        layout, dev = self.layout, self.device
        static, self.robots = robot_embodiment(layout, self.trained.normalizer, ctx.models, dev)
        if "control" in getattr(self.model, "anchors", {}):  # stand-in networks of the tests have none
            from tt.dit.anchors import check_joint_actuators

            check_joint_actuators(self.robots, ctx.models)
        self._static = {n: (static.values[n], static.ids[n], static.mask[n]) for n in static.values}
        for s in layout.specs:
            if s.role in STEP_ROLES:
                widest = max(_step_count(s.name, r) for r in self.robots)
                if widest > s.per_step:
                    raise LayoutError(
                        f"a design has {widest} {s.name} tokens per step; the model's layout holds {s.per_step}"
                    )
        P = layout["control"].per_step
        act = torch.full((len(self.robots), P), -1, dtype=torch.long)
        for d, r in enumerate(self.robots):
            act[d, : len(r.actuator_mj)] = torch.as_tensor(np.asarray(r.actuator_mj), dtype=torch.long)
        self._actuator = act.to(ctx.target_pos.device)  # (D, P): MuJoCo actuator of each control slot
        self.generator = torch.Generator(device=dev).manual_seed(int(self.config.seed))
        self._chunks: list[tuple[int, torch.Tensor]] = []  # (step, (W, S, P) commands) of the recent queries

    def query(self, step: int, worlds: torch.Tensor, state: StepState) -> tuple[TokenBatch, int]:
        """Normalised control-task tokens of worlds `worlds` at control step `step`, and the
        window slot whose command is executed (1, or 0 at step 0)."""
        from tt.tokens.episodes import episode_tokens

        ctx, layout, norm = self.ctx, self.layout, self.trained.normalizer
        S = layout.steps
        start = max(step - 1, 0)
        slot = 1 if step >= 1 else 0
        n = len(worlds)
        horizon = ctx.target_pos.shape[1]
        idx = torch.clamp(torch.arange(start, start + S, device=worlds.device), max=horizon - 1)
        aim = torch.clamp(
            idx + self.task.target_offset, max=horizon - 1
        )  # the targets given (`tt.dit.tasks.look_ahead`)
        # An S-step episode whose every record is the current state: the tokens of its first
        # step are the window's clean state; the later ones are diffused (their values unused).
        rep = lambda x: x[worlds][:, None].expand(n, S, *x.shape[1:]).contiguous()  # noqa: E731
        ep = Episode(
            qpos=rep(state.qpos), qvel=rep(state.qvel), ctrl=rep(state.ctrl), action=rep(state.ctrl),
            act_force=rep(state.act_force), act_vel=rep(state.act_vel),
            ee_pos=rep(state.ee_pos), ee_quat=rep(state.ee_quat),
            target_pos=ctx.target_pos[worlds][:, aim], target_quat=ctx.target_quat[worlds][:, aim],
            alive=torch.ones(n, S, dtype=torch.bool, device=worlds.device),
            fallen=torch.zeros(n, S, dtype=torch.bool, device=worlds.device),
            design_index=ctx.design_index[worlds], motion_index=ctx.motion_index[worlds], dt=ctx.config.control_dt,
        )  # fmt: skip
        window = episode_tokens(ep, self.robots, step_index=torch.arange(S, device=worlds.device).expand(n, S))
        dev = self.device
        design = ctx.design_index[worlds].to(dev)
        values, ids, mask = {}, {}, {}
        for s in layout.specs:
            if s.role not in STEP_ROLES:
                v, i, m = self._static[s.name]
                values[s.name], ids[s.name], mask[s.name] = v[design], i[design], m[design]
                continue
            P = s.per_step
            if s.name in window.values:
                v = window.values[s.name].to(dev)
                e = v.shape[1] // S
                v = v.reshape(n, S, e, -1)
                i = window.ids[s.name].to(dev).reshape(n, S, e, -1)
                m = window.mask[s.name].to(dev).reshape(n, S, e)
            else:  # a type none of these designs has: all padding
                e = 0
                v = torch.zeros(n, S, 0, s.dim, device=dev)
                i = torch.zeros(n, S, 0, len(s.ids), dtype=torch.long, device=dev)
                m = torch.zeros(n, S, 0, dtype=torch.bool, device=dev)
            pad = P - e
            v = torch.cat([v, v.new_zeros(n, S, pad, s.dim)], 2)
            i = torch.cat([i, i.new_zeros(n, S, pad, len(s.ids))], 2)
            m = torch.cat([m, m.new_zeros(n, S, pad)], 2)
            i[..., s.time_index] = torch.arange(start, start + S, device=dev)[None, :, None]
            values[s.name] = norm.normalize_values(s.name, v.reshape(n, S * P, s.dim), m.reshape(n, S * P))
            ids[s.name] = i.reshape(n, S * P, -1)
            mask[s.name] = m.reshape(n, S * P)
        return TokenBatch(values, ids, mask), slot

    def __call__(self, step: int, worlds: torch.Tensor, state: StepState) -> torch.Tensor:
        from tt.dit.ddim import CosineDDIM

        tokens, slot = self.query(step, worlds, state)
        c = self.config
        with torch.no_grad():
            res = sample(
                self.model,
                tokens,
                self.task,
                scheduler=CosineDDIM(self.task.diffusion_steps),
                num_steps=c.num_steps,
                eta=c.eta,
                generator=self.generator,
                spacing=c.spacing,
            )
        if self.ensemble == 1:
            return self.commands(worlds, state, self.control_slot(res.tokens, slot))
        return self.commands(worlds, state, self._ensembled(step, worlds, self.control_chunk(res.tokens)))

    def _ensembled(self, step: int, worlds: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        """(n, P) weighted mean of step `step`'s command over the current query's `chunk`
        (n, S, P) and the chunks of the last ``ensemble - 1`` queries."""
        S, P = chunk.shape[1], chunk.shape[2]
        rows = worlds.to(chunk.device)
        full = torch.full((self.ctx.world_count, S, P), float("nan"), device=chunk.device)
        full[rows] = chunk
        self._chunks = [c for c in self._chunks if step - c[0] < self.ensemble]
        self._chunks.append((step, full))
        total = torch.zeros(len(rows), P, device=chunk.device)
        weight = torch.zeros(len(rows), 1, device=chunk.device)
        for k, c in self._chunks:
            # (n, P): step `step`'s slot in the window of query k (which starts at k - 1); NaN
            # rows: worlds that query did not run.
            pred = c[rows, step - max(k - 1, 0)]
            w = torch.where(torch.isnan(pred[:, :1]), 0.0, float(np.exp(-self.config.ensemble_decay * (step - k))))
            total += w * torch.nan_to_num(pred)
            weight += w
        return total / weight

    def control_chunk(self, tokens: TokenBatch) -> torch.Tensor:
        """(n, S, P) denormalised commands [rad or m] of every window slot of normalised tokens."""
        P = self.layout["control"].per_step
        out = tokens.values["control"].reshape(len(tokens), self.layout.steps, P, -1)  # (n, S, P, 1)
        return self.trained.normalizer.denormalize_values("control", out.float())[..., 0]

    def control_slot(self, tokens: TokenBatch, slot: int) -> torch.Tensor:
        """(n, P) denormalised commands [rad or m] of window slot `slot` of normalised tokens."""
        return self.control_chunk(tokens)[:, slot]

    def commands(self, worlds: torch.Tensor, state: StepState, target: torch.Tensor) -> torch.Tensor:
        """The worlds' actuator commands (n, nu): the last ones, with each real control slot's
        `target` (n, P) written into the actuator it drives."""
        target = target.to(worlds.device)
        n, P = target.shape
        act = self._actuator[self.ctx.design_index[worlds]]  # (n, P)
        ctrl = state.ctrl[worlds].clone()
        rows = torch.arange(n, device=worlds.device)[:, None].expand(n, P)
        real = act >= 0
        ctrl[rows[real], act[real]] = target[real].to(ctrl.dtype)
        return ctrl[:, : self.ctx.worlds.nu]


def _step_count(name: str, robot) -> int:
    """Tokens per control step of per-step type `name` for one tokenized robot."""
    counts = robot.counts
    key = {
        "free_link_obs": "free_link",
        "track_link_obs": "track_link",
        "dyna_joint_obs": "dyna_joint",
        "ball_joint_obs": "ball_joint",
        "actuator_obs": "actuator",
        "control": "actuator",
        "target_pose": "track_link",
    }.get(name)
    return counts[key] if key is not None else 0


def model_rollout(
    designs,
    motions: Sequence[Motion],
    model: TrainedModel | str | Path,
    *,
    config: ControllerConfig = ControllerConfig(),
    task: TaskSpec | None = None,
    ik_config: IKConfig = IKConfig(),
    device: str | None = None,
    steps: int | None = None,
    progress: bool = False,
) -> Episode:
    """`closed_loop_rollout` with the DiT as the controller.

    model: a loaded model, or a checkpoint file / run folder (loaded with EMA weights on
    `device`; its control task read from the checkpoint); task: the control task (default:
    the checkpoint's, or `tt.dit.tasks.CONTROL` for a loaded model).
    """
    if not isinstance(model, TrainedModel):
        import warp as wp

        from tt.kernels.device import resolve_device

        task = control_task(model) if task is None else task
        model = load_model(model, device=str(wp.device_to_torch(resolve_device(device))))
    policy = ModelPolicy(model, task=task or CONTROL, config=config)
    return closed_loop_rollout(
        designs, motions, policy, config=ik_config, device=device, steps=steps, progress=progress
    )


__all__ = [
    "CONTROLLERS",
    "ControllerConfig",
    "HoldPolicy",
    "IKPolicy",
    "ModelPolicy",
    "control_task",
    "control_task_of",
    "model_rollout",
]
