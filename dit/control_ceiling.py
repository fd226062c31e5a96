"""A supervised ceiling for the control task: a regressor fitted to DiffIK's next command on
exactly the clean conditions of the DiT controller's query (`tt.dit.policies.ModelPolicy`),
and run in closed loop as the DiT is run.

The benchmark ``benchmarks/control_ceiling.py`` drives it (training sizes, variants, the
report); this module holds what it fits and measures, so that its tests import it from the
package: the variants' grammar (`Variant`), the features of a control window (`features`,
`design_columns`), the windows (`Windows`, `draw_windows`, `trimmed`), the regressors
(`Regressor`, `FiLMRegressor`, `fit`, `one_step`), the closed-loop policy
(`regressor_policy`), DAgger (`dagger_windows`), a pool of known designs (`DesignPool`) and
DiffIK with command noise (`NoisyIK`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tt.kernels.errors import TTError

#: Steps of a control window (the DiT's layout).
STEPS = 8
ANCHORS = ("command", "joints")
LOSSES = ("mse", "huber")


@dataclass(frozen=True)
class Variant:
    """How the regressor is set up: anchor (`ANCHORS`), loss (`LOSSES`), DAgger rounds, model
    ("mlp": `Regressor`, the default; "film": `FiLMRegressor`)."""

    anchor: str = "command"
    loss: str = "mse"
    dagger: int = 0
    model: str = "mlp"

    @classmethod
    def parse(cls, text: str) -> "Variant":
        """``ANCHOR/LOSS[/film][/daggerK]``, e.g. ``joints/huber/film/dagger2``."""
        parts = text.strip().split("/")
        if len(parts) not in (2, 3, 4) or parts[0] not in ANCHORS or parts[1] not in LOSSES:
            raise TTError(
                f"variant {text!r}: expected ANCHOR/LOSS[/film][/daggerK] with ANCHOR in {ANCHORS}, LOSS in {LOSSES}"
            )
        rest, model, rounds = parts[2:], "mlp", 0
        if rest and rest[0] == "film":  # the plain MLP is the default, never named
            model = rest.pop(0)
        if rest:
            last = rest.pop(0)
            if not last.startswith("dagger") or not last[6:].isdigit() or int(last[6:]) < 1:
                raise TTError(f"variant {text!r}: the last part is daggerK with K >= 1")
            rounds = int(last[6:])
        if rest:
            raise TTError(f"variant {text!r}: expected ANCHOR/LOSS[/film][/daggerK]")
        return cls(parts[0], parts[1], rounds, model)

    @property
    def label(self) -> str:
        return (
            f"{self.anchor}/{self.loss}"
            + (f"/{self.model}" if self.model != "mlp" else "")
            + (f"/dagger{self.dagger}" if self.dagger else "")
        )


def feature_blocks(layout, command: bool = True) -> list[tuple]:
    """The blocks of `features`, in order, as (spec, whole, width): embodiment types and the
    target poses whole (all their tokens), the other per-step types at step 0 only, the last
    command only with `command`; width: the block's columns."""
    from tt.tokens.schema import STEP_ROLES

    out = []
    for s in layout.specs:
        whole = s.role not in STEP_ROLES or s.name == "target_pose"
        if whole or s.name != "control" or command:
            out.append((s, whole, s.dim * (s.length if whole else s.per_step)))
    return out


def features(tokens, layout, command: bool = True) -> torch.Tensor:
    """(n, F) float32: the control query's clean conditions of normalised windows `tokens`
    (padding at PAD_VALUE, as the DiT reads it): every embodiment token, step 0 of every
    per-step type (the current state and, with `command`, the last command) and the target
    poses of all steps."""
    parts = []
    for s, whole, _ in feature_blocks(layout, command):
        v = tokens.values[s.name].float()
        parts.append(v.reshape(len(v), -1) if whole else v.reshape(len(v), layout.steps, -1)[:, 0])
    return torch.cat(parts, 1)


def command_free(layout) -> torch.Tensor:
    """(F',) long: the columns of `features` that `features(..., command=False)` keeps, i.e.
    all but the last command's."""
    keep, at = [], 0
    for s, _, width in feature_blocks(layout):
        if s.name != "control":
            keep.append(torch.arange(at, at + width))
        at += width
    return torch.cat(keep)


def design_columns(layout, command: bool = True) -> torch.Tensor:
    """(F,) bool: which columns of `features(..., command)` are embodiment tokens (the design)."""
    from tt.tokens.schema import STEP_ROLES

    return torch.cat(
        [torch.full((width,), s.role not in STEP_ROLES) for s, _, width in feature_blocks(layout, command)]
    )


def commands(raw, layout) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Raw windows -> (c0, c1, real): the last and next commands (n, P) [rad] and the joint
    slots both are real in (n, P)."""
    P = layout["control"].per_step
    n = raw.values["control"].shape[0]
    c = raw.values["control"].reshape(n, layout.steps, P).float()
    m = raw.mask["control"].reshape(n, layout.steps, P)
    return c[:, 0], c[:, 1], m[:, 0] & m[:, 1]


def window_joints(values, layout) -> torch.Tensor:
    """(n, P) joint positions of window step 0 (the current state) from raw or denormalised
    ``dyna_joint_obs`` values, in control-slot order (a ViperX joint slot is its actuator's)."""
    P = layout["control"].per_step
    return values.reshape(len(values), layout.steps, -1, 2)[:, 0, :P, 0].float()


@dataclass
class Windows:
    """Control windows as the regressor reads them: features (n, F), last and next command
    c0, c1 (n, P) [rad], the slots real in both (n, P) bool, the current joint positions q
    (n, P) [rad] and the feature columns without the last command, `command_free` (F',)."""

    X: torch.Tensor
    c0: torch.Tensor
    c1: torch.Tensor
    real: torch.Tensor
    q: torch.Tensor
    free: torch.Tensor

    @classmethod
    def of(cls, raw, layout, norm, labels=None) -> "Windows":
        """Windows of raw tokens; `labels`: the same windows with DiffIK's commands as control
        tokens (DAgger), which then give the next command while `raw`'s (what was executed)
        give the last one and the features."""
        tokens = norm.normalize(raw)
        c0, c1, real = commands(raw, layout)
        if labels is not None:
            _, c1, real_next = commands(labels, layout)
            real = real & real_next
        return cls(
            features(tokens, layout),
            c0,
            c1,
            real,
            window_joints(raw.values["dyna_joint_obs"], layout),
            command_free(layout),
        )

    @classmethod
    def cat(cls, parts: list["Windows"]) -> "Windows":
        return cls(*(torch.cat([getattr(w, f) for w in parts]) for f in ("X", "c0", "c1", "real", "q")), parts[0].free)

    def __len__(self) -> int:
        return len(self.c0)

    def take(self, rows) -> "Windows":
        return Windows(self.X[rows], self.c0[rows], self.c1[rows], self.real[rows], self.q[rows], self.free)

    def inputs(self, variant: Variant) -> torch.Tensor:
        """(n, F) or, for the joints anchor, (n, F') features (a copy without the command's columns)."""
        return self.X if variant.anchor == "command" else self.X[:, self.free]

    def anchor(self, variant: Variant) -> torch.Tensor:
        return self.c0 if variant.anchor == "command" else self.q


class Regressor(torch.nn.Module):
    """MLP: features -> the next command's offset from its anchor, in units of `scale` (P,)."""

    def __init__(
        self,
        width_in: int,
        joints: int,
        scale: torch.Tensor,
        mean: torch.Tensor,
        std: torch.Tensor,
        hidden: int = 512,
        depth: int = 3,
    ):
        super().__init__()
        layers, w = [], width_in
        for _ in range(depth):
            layers += [torch.nn.Linear(w, hidden), torch.nn.GELU()]
            w = hidden
        layers.append(torch.nn.Linear(w, joints))
        self.net = torch.nn.Sequential(*layers)
        self.register_buffer("scale", scale)
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(n, F) features -> (n, P) offsets [rad]."""
        return self.net((x - self.mean) / self.std) * self.scale


class FiLMRegressor(torch.nn.Module):
    """An MLP over the columns other than the embodiment's (the state, the targets and, with
    the command anchor, the last command) whose every hidden layer the design scales and shifts
    (FiLM): h <- GELU((W h + b)(1 + gamma(d)) + beta(d)), gamma and beta from an MLP of the
    embodiment columns `design` (F,) bool. DiffIK's increment is a design-dependent linear map
    of the tracking error; a plain MLP must build such products from sums, this one has them.
    The modulation starts at zero, so it starts as the plain MLP of the non-design columns."""

    def __init__(
        self,
        design: torch.Tensor,
        joints: int,
        scale: torch.Tensor,
        mean: torch.Tensor,
        std: torch.Tensor,
        hidden: int = 512,
        depth: int = 3,
    ):
        super().__init__()
        self.register_buffer("design", design.nonzero()[:, 0])
        self.register_buffer("state", (~design).nonzero()[:, 0])
        self.layers = torch.nn.ModuleList(
            torch.nn.Linear(len(self.state) if k == 0 else hidden, hidden) for k in range(depth)
        )
        self.cond = torch.nn.Sequential(
            torch.nn.Linear(len(self.design), hidden), torch.nn.GELU(), torch.nn.Linear(hidden, 2 * hidden * depth)
        )
        torch.nn.init.zeros_(self.cond[-1].weight)
        torch.nn.init.zeros_(self.cond[-1].bias)
        self.out = torch.nn.Linear(hidden, joints)
        self.register_buffer("scale", scale)
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(n, F) features -> (n, P) offsets [rad]."""
        z = (x - self.mean) / self.std
        film = self.cond(z[:, self.design]).chunk(2 * len(self.layers), 1)
        h = z[:, self.state]
        for k, layer in enumerate(self.layers):
            h = torch.nn.functional.gelu(layer(h) * (1 + film[2 * k]) + film[2 * k + 1])
        return self.out(h) * self.scale


def draw_windows(source, n: int, layout, norm, seed: int, chunk: int = 8192, refreshes: int = 1) -> Windows:
    """n raw windows of `source`, an equal share from each of its first `refreshes` online
    refreshes (one held at a time, so memory stays one refresh's), in a random order."""
    from tt.dit.tasks import CONTROL, task_windows

    gen = torch.Generator().manual_seed(seed)
    shares = [n // refreshes + (k < n % refreshes) for k in range(refreshes)]
    draws = []
    for k, share in enumerate(shares):
        if refreshes > 1:
            source.start_step(k * source.config.refresh_every)
        for a in range(0, share, chunk):
            draws.append(Windows.of(task_windows(source, layout, min(chunk, share - a), CONTROL, gen), layout, norm))
    # Shuffled into place chunk by chunk, each freed once placed: at a million windows the
    # features are gigabytes, and concatenating then permuting would hold three copies.
    order = torch.empty(n, dtype=torch.long)
    order[torch.randperm(n, generator=gen)] = torch.arange(n)
    fields = ("X", "c0", "c1", "real", "q")
    first = draws[0]
    out = Windows(
        *(
            torch.empty(
                (n, *getattr(first, f).shape[1:]), dtype=getattr(first, f).dtype, device=getattr(first, f).device
            )
            for f in fields
        ),
        first.free,
    )
    at = 0
    while draws:
        part = draws.pop(0)
        rows = order[at : at + len(part)]
        for f in fields:
            getattr(out, f)[rows] = getattr(part, f)
        at += len(part)
    return out


def fit(
    data: Windows,
    variant: Variant,
    *,
    epochs: float,
    batch: int,
    lr: float,
    seed: int,
    huber_delta: float = 0.1,
    layout=None,
    hidden: int = 512,
    depth: int = 3,
) -> tuple[torch.nn.Module, list[float]]:
    """The variant's loss on the offsets from its anchor, in units of each joint slot's RMS
    offset, masked to real slots; AdamW, one-cycle schedule. `layout` (the windows') tells a
    FiLM model its design columns."""
    torch.manual_seed(seed)
    X, cols = data.X, (None if variant.anchor == "command" else data.free)
    # The joints anchor's columns are picked per batch: a copy of X without the command
    # would double the memory at a million windows.
    mean, std = X.mean(0), X.std(0).clamp_min(1e-3)
    if cols is not None:
        mean, std = mean[cols], std[cols]
    y = torch.where(data.real, data.c1 - data.anchor(variant), torch.zeros_like(data.c0))
    scale = (y.pow(2).sum(0) / data.real.sum(0).clamp_min(1)).sqrt().clamp_min(1e-4)
    if variant.model == "film":
        if layout is None:
            raise TTError("fit: a FiLM variant needs the windows' layout")
        model = FiLMRegressor(
            design_columns(layout, command=variant.anchor == "command"),
            y.shape[1],
            scale,
            mean,
            std,
            hidden=hidden,
            depth=depth,
        )
    else:
        model = Regressor(len(mean), y.shape[1], scale, mean, std, hidden=hidden, depth=depth)
    steps = max(1, int(epochs * len(X) // batch))
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.05)
    gen = torch.Generator().manual_seed(seed)
    losses = []
    for k in range(steps):
        i = torch.randint(0, len(X), (batch,), generator=gen)
        m = data.real[i].float()
        err = (model(X[i] if cols is None else X[i][:, cols]) - y[i]) / model.scale
        if variant.loss == "huber":
            per = torch.nn.functional.huber_loss(err, torch.zeros_like(err), reduction="none", delta=huber_delta)
        else:
            per = err.pow(2)
        loss = (per * m).sum() / m.sum().clamp_min(1)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
    return model.eval(), losses


def one_step(model: torch.nn.Module, data: Windows, variant: Variant) -> dict:
    """RMSE [rad] of the next command: the regressor's, holding the current joints', repeating
    the last command's; R^2 of the offset from the last command, over all windows and over
    the typical ones (each slot's offsets up to its 99th percentile)."""
    with torch.no_grad():
        pred = data.anchor(variant) + model(data.inputs(variant))
    real, c1 = data.real, data.c1
    rmse = lambda e: float(e[real].pow(2).mean().sqrt())  # noqa: E731
    y = c1 - data.c0
    typical = real & (y.abs() <= tail_quantile(y, real, 0.99))
    return {
        "rmse": rmse(pred - c1),
        "hold": rmse(data.q - c1),
        "repeat": rmse(data.c0 - c1),
        "r2": float(1 - (pred - c1)[real].pow(2).mean() / y[real].pow(2).mean()),
        "r2_typical": float(1 - (pred - c1)[typical].pow(2).mean() / y[typical].pow(2).mean()),
    }


def tail_quantile(y: torch.Tensor, real: torch.Tensor, q: float) -> torch.Tensor:
    """(P,) per-slot quantile `q` of |y| over real entries (inf where a slot has none)."""
    out = torch.full((y.shape[1],), float("inf"))
    for j in range(y.shape[1]):
        if bool(real[:, j].any()):
            out[j] = y[:, j][real[:, j]].abs().quantile(q)
    return out


def trimmed(data: Windows, variant: Variant, q: float) -> Windows:
    """`data` without the windows whose offset from the variant's anchor exceeds, in any real
    slot, that slot's quantile `q` of |offset| (q = 1: all of them)."""
    if q >= 1.0:
        return data
    y = data.c1 - data.anchor(variant)
    out = (data.real & (y.abs() > tail_quantile(y, data.real, q))).any(1)
    return data.take((~out).nonzero()[:, 0])


def tail_share(y: torch.Tensor, real: torch.Tensor, top: float) -> float:
    """Share of the summed squares of y's real entries carried by the largest `top` fraction, pooled over slots."""
    v = y[real].pow(2).sort(descending=True).values
    return float(v[: max(1, int(top * len(v)))].sum() / v.sum().clamp_min(1e-30))


def regressor_policy(model: torch.nn.Module, layout, norm, variant: Variant, space: str, labels: bool = False):
    """A closed-loop policy (`tt.dit.closed_loop.Policy`) that builds the DiT controller's query
    (`ModelPolicy.query`) and executes the variant's anchor plus the regressor's offset.

    It also calls DiffIK (`IKPolicy`) on every state it visits: ``moved`` / ``ik_moved`` sum
    the mean |offset from the anchor| of its commands and of DiffIK's over steps (real slots),
    and with `labels` it keeps DiffIK's commands, (W, T, nu), for DAgger."""
    from tt.dit.checkpoint import TrainedModel
    from tt.dit.policies import IKPolicy, ModelPolicy

    class RegressorPolicy(ModelPolicy):
        def reset(self, ctx):
            super().reset(ctx)
            self.ik = IKPolicy()
            self.ik.reset(ctx)
            self.moved, self.ik_moved, self.labels = 0.0, 0.0, None
            if labels:
                self.labels = torch.zeros(ctx.world_count, int(ctx.motion_steps.max()), ctx.worlds.nu)

        def __call__(self, step, worlds, state):
            tokens, slot = self.query(step, worlds, state)
            c0 = self.control_slot(tokens, 0)  # the last command (given: step 0 of the window)
            ik = self.ik(step, worlds, state)  # (n, nu)
            if self.labels is not None:
                self.labels[worlds, step] = ik.float().cpu()
            if slot == 0:
                return self.commands(worlds, state, c0)
            if variant.anchor == "command":
                anchor = c0
            else:
                joint_obs = self.trained.normalizer.denormalize_values(
                    "dyna_joint_obs", tokens.values["dyna_joint_obs"].float()
                )
                anchor = window_joints(joint_obs, self.layout)
            with torch.no_grad():
                target = anchor + model(features(tokens, self.layout, command=variant.anchor == "command"))
            act = self._actuator[self.ctx.design_index[worlds]]  # (n, P) actuator of each slot, -1: none
            real = act >= 0
            ik_slots = torch.gather(ik, 1, act.clamp_min(0))
            self.moved += float((target - anchor)[real].abs().mean())
            self.ik_moved += float((ik_slots - anchor)[real].abs().mean())
            return self.commands(worlds, state, target)

    return RegressorPolicy(
        TrainedModel(model=model, normalizer=norm, layout=layout, step=0, space=space, tasks=("control",))
    )


def dagger_windows(
    source, k: int, model: torch.nn.Module, layout, norm, variant: Variant, n: int, seed: int
) -> tuple[Windows, dict]:
    """DAgger: the regressor controls refresh `k`'s designs x motions of `source`; every state it
    visits is labelled with DiffIK's command from that state (the episode's ``action``, which
    the control tokens read). Returns n windows of those episodes and their statistics."""
    from tt.dit.closed_loop import closed_loop_rollout
    from tt.dit.online import episode_token_batch
    from tt.dit.tasks import CONTROL, task_windows
    from tt.tokens.tokenize import Tokenizer

    designs, motions = source.draw(k)
    policy = regressor_policy(model, layout, norm, variant, labels=True, space=source.config.space)
    ep = closed_loop_rollout(designs, motions, policy)
    embodiment = Tokenizer()([source.space.model(d) for d in designs])
    lengths = ep.lengths()
    keep = (lengths >= STEPS).nonzero()[:, 0]
    if not len(keep):
        raise RuntimeError(f"DAgger refresh {k}: every episode ended within {STEPS} steps")
    raws = []
    # Twice, the same windows: control tokens of what was executed (the last command, read by
    # the command anchor) and of DiffIK's labels (the next command).
    for action in (ep.ctrl, policy.labels[:, : ep.steps].to(ep.ctrl.device)):
        ep.action = action
        episodes = episode_token_batch(ep, embodiment, lengths, keep, source.config.max_time, source.maxima)
        raws.append(task_windows(episodes, layout, n, CONTROL, torch.Generator().manual_seed(seed)))
    windows = Windows.of(raws[0], layout, norm, labels=raws[1])
    return windows, {"episodes": ep.worlds, "kept": len(keep), "mean_steps": float(lengths.float().mean())}


class DesignPool:
    """A design space whose every draw cycles through a fixed pool of designs (`--pool`): the
    online source then rolls those designs out on fresh motions. Everything else is the
    wrapped space's."""

    def __init__(self, space, designs):
        self._space, self.designs = space, list(designs)

    def sample(self, n: int, seed=None) -> list:
        return [self.designs[i % len(self.designs)] for i in range(n)]

    def __getattr__(self, name):
        return getattr(self._space, name)


class NoisyIK:
    """DiffIK with independent Gaussian noise of `sigma` [rad] on every command."""

    def __init__(self, sigma: float, seed: int = 0):
        from tt.dit.policies import IKPolicy

        self.sigma, self.ik = sigma, IKPolicy()
        self.generator = torch.Generator().manual_seed(seed)

    def reset(self, ctx) -> None:
        self.ik.reset(ctx)

    def __call__(self, step, worlds, state):
        cmd = self.ik(step, worlds, state)
        return cmd + self.sigma * torch.randn(cmd.shape, generator=self.generator).to(cmd.device)
