"""DDIM sampling loop with a guidance hook.

`sample` starts every token the task diffuses from Gaussian noise, keeps every other token
(conditioning, masked padding) exactly at its given value, and runs the reverse DDIM
steps. At each step it computes the model's eps and the predicted clean tokens x0_hat,
then, when a `guide` is given, calls

    guide(step, x_t, eps, x0_hat) -> eps'

with dicts type -> (B, L, D) in normalised units. `step` counts from 0 (the noisiest);
`t = timesteps[step]` and alpha_bar_t are available from the scheduler
(`scheduler.timesteps(n)`, `scheduler.alpha_bar(t)`, `scheduler.guided_eps`). With
``guide_grad=True`` (the default when guiding) x_t are leaf tensors that require grad and
eps, x0_hat are built from them with autograd on, so a guide can differentiate a reward of
x0_hat through the network: ``g = torch.autograd.grad(R(x0_hat), x_t)``, then return
``scheduler.guided_eps(eps, g, s, t)`` (Dynamics Self-Guidance). The guide may return a
subset of types; eps' replaces eps only on guided tokens (``guided``: which types, or
per-type (B, L) masks; default all diffused types) and never on tokens that are not
diffused. x0_hat is clipped to the data range (+-1), as the step uses it.

The network may predict eps, x0 or v (its ``prediction``, `tt.dit.ddim.PREDICTIONS`); its
output is turned into eps (`CosineDDIM.eps_from_output`) before anything else reads it.

Inpainting (``known``): tokens the task diffuses but whose clean values are given, e.g. a
design's embodiment tokens when the motion-to-robot model is asked only for that design's
dynamics. Before each network call they are set to their given value noised to the
current step's level, q(x_t | x0) with fresh noise (the replacement method; the network
sees them as it saw diffused tokens in training), and the result holds their given values.

Differentiable sampling (``differentiable=True``, no guide; under ``torch.no_grad`` it
samples as usual): autograd stays on through every step, the denoised tokens are not
detached between steps, and the result's tokens carry the graph back to the given
conditioning values, the clean slots of diffused types included (the given values of the
diffused slots only decide where the noise goes). A conditioning value that requires grad
then gets the gradient of anything computed from the sample, e.g. a dynamics critic's
predicted reward with respect to the design it is given (`tt.guidance.critic_grad`). The
noise comes from `generator` as without it, so both modes draw the same sample.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Mapping

import torch
from tqdm import tqdm

from tt.dit.ddim import CosineDDIM
from tt.dit.model import RoboDiT
from tt.dit.tasks import TaskSpec, output_types, task_masks
from tt.kernels.errors import TTError
from tt.tokens.batch import TokenBatch

#: guide(step, x_t, eps, x0_hat) -> eps' (dicts type -> (B, L, D)).
GuideFn = Callable[
    [int, dict[str, torch.Tensor], dict[str, torch.Tensor], dict[str, torch.Tensor]], Mapping[str, torch.Tensor]
]


@dataclass
class SampleResult:
    """tokens: final normalised tokens (ids and mask as given); updated: type -> (B, L) bool,
    the tokens that were diffused; x0_history: per step, the predicted clean tokens
    (detached), when requested."""

    tokens: TokenBatch
    updated: dict[str, torch.Tensor]
    x0_history: list[dict[str, torch.Tensor]] | None = None


def _guided_masks(guided, updated: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    if guided is None:
        return updated
    if isinstance(guided, Mapping):
        unknown = [k for k in guided if k not in updated]
        if unknown:
            raise TTError(f"guided names types {unknown} that this task does not diffuse; diffused: {sorted(updated)}")
        return {k: updated[k] & guided[k].to(updated[k].device) for k in guided}
    names = list(guided)
    unknown = [k for k in names if k not in updated]
    if unknown:
        raise TTError(f"guided names types {unknown} that this task does not diffuse; diffused: {sorted(updated)}")
    return {k: updated[k] for k in names}


def sample(
    model: RoboDiT,
    tokens: TokenBatch,
    task: TaskSpec,
    *,
    scheduler: CosineDDIM | None = None,
    num_steps: int | None = None,
    eta: float = 0.0,
    generator: torch.Generator | None = None,
    guide: GuideFn | None = None,
    guided: Iterable[str] | Mapping[str, torch.Tensor] | None = None,
    guide_grad: bool = True,
    keep_x0: bool = False,
    bf16: bool = False,
    known: Mapping[str, torch.Tensor] | None = None,
    differentiable: bool = False,
    spacing: str = "leading",
    init_noise: Mapping[str, torch.Tensor] | None = None,
    temperature: float = 1.0,
    progress: bool = False,
) -> SampleResult:
    """Denoise the tokens `task` diffuses, conditioned on the others.

    model: the network (use EMA weights); tokens: normalised tokens of B sequences whose
    conditioning values are set (values of diffused tokens are ignored); scheduler: defaults
    to ``CosineDDIM(task.diffusion_steps)``; num_steps: sampling steps (default all T);
    eta: DDIM noise (0 deterministic, 1 DDPM-like; the paper uses 1 for self-guidance);
    generator: on the tokens' device, for the initial noise and eta > 0; guide, guided,
    guide_grad: see the module docstring; keep_x0: record x0_hat per step; bf16: autocast
    the network to bfloat16 (CUDA only); known: type -> (B, L) bool, diffused tokens whose
    given values are kept (inpainting, see the module docstring); differentiable: keep the
    graph through every step (see the module docstring; not with a guide); spacing: of the
    num_steps sampling steps (`CosineDDIM.timesteps`); init_noise: type -> (B, L, D) starting
    noise of diffused types, in place of `generator`'s draw (types left out are drawn), so
    callers can give several sequences the same noise (common random numbers); temperature:
    scale of the drawn starting noise (1: the model's distribution; below 1 moves deterministic
    DDIM's samples towards the modes, a common trade of diversity for quality); progress: a
    tqdm bar over the sampling steps.
    """
    layout = model.layout
    layout.check(tokens)
    scheduler = CosineDDIM(task.diffusion_steps) if scheduler is None else scheduler
    if scheduler.train_steps != task.diffusion_steps:
        raise TTError(
            f"task {task.name!r} diffuses over {task.diffusion_steps} steps, the scheduler over {scheduler.train_steps}"
        )
    if eta < 0:
        raise TTError(f"eta must be >= 0, got {eta}")
    if not temperature > 0:
        raise TTError(f"temperature must be > 0, got {temperature}")
    if differentiable and guide is not None:
        raise TTError(
            "differentiable sampling keeps one graph through every step; a guide differentiates each step "
            "on its own (give one or the other)"
        )
    differentiable = differentiable and torch.is_grad_enabled()
    keep = (lambda v: v) if differentiable else torch.Tensor.detach  # what crosses a step keeps its graph or not
    device = tokens.device
    b = len(tokens)
    masks = task_masks(task, layout, tokens)
    wanted = output_types(task, layout)
    updated = {n: masks.noised[n] & masks.visible[n] for n in wanted}
    guided_masks = _guided_masks(guided, updated) if guide is not None else {}
    stray = sorted(set(init_noise or ()) - set(updated))
    if stray:
        raise TTError(f"init_noise names types {stray} that this task does not diffuse; diffused: {sorted(updated)}")
    given = {}
    for n, m in (known or {}).items():
        if n not in updated:
            raise TTError(f"known names type {n!r}, which this task does not diffuse; diffused: {sorted(updated)}")
        m = m.to(device).bool() & updated[n]
        updated[n] = updated[n] & ~m
        given[n] = (m, tokens.values[n].float())
    x = {}
    for s in layout.specs:
        v = tokens.values[s.name]
        if s.name in updated:
            if init_noise is not None and s.name in init_noise:
                noise = init_noise[s.name].to(device=device, dtype=torch.float32)
                if noise.shape != v.shape:
                    raise TTError(
                        f"init_noise[{s.name!r}] has shape {tuple(noise.shape)}; the tokens' is {tuple(v.shape)}"
                    )
            else:
                noise = temperature * torch.randn(v.shape, generator=generator, device=device, dtype=torch.float32)
            # Clean slots of a diffused type (a window's given first step) are conditions too.
            x[s.name] = torch.where(updated[s.name].unsqueeze(-1), noise, keep(v.float()))
        else:
            x[s.name] = keep(v.float())
    steps = scheduler.timesteps(num_steps, spacing)
    history = [] if keep_x0 else None
    use_grad = (guide is not None and guide_grad) or differentiable
    prediction = getattr(model, "prediction", "eps")
    autocast = torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=bf16 and device.type == "cuda")
    bar = tqdm(steps, desc=f"sampling {b} sequences", unit="step", leave=False, disable=not progress)
    for i, t in enumerate(bar):
        t_prev = steps[i + 1] if i + 1 < len(steps) else -1
        time = torch.full((b,), float(scheduler.model_time(t)), device=device)
        for n, (m, x0_given) in given.items():
            noise = torch.randn(x0_given.shape, generator=generator, device=device, dtype=torch.float32)
            x[n] = torch.where(m.unsqueeze(-1), scheduler.add_noise(x0_given, noise, t), x[n])
        if differentiable:
            x_in = x
        else:
            x_in = {n: (v.detach().requires_grad_(n in updated) if use_grad else v) for n, v in x.items()}
        with torch.set_grad_enabled(use_grad), autocast:
            out = model(x_in, tokens.ids, masks.noised, time, masks.attend, outputs=wanted)
        with torch.set_grad_enabled(use_grad):
            eps = {n: scheduler.eps_from_output(e.float(), x_in[n], t, prediction) for n, e in out.items()}
            x0 = {n: scheduler.predict_x0(x_in[n], eps[n], t) for n in wanted}
            if guide is not None:
                new = guide(i, x_in, eps, x0)
                for n, e in new.items():
                    if n not in guided_masks:
                        continue
                    if e.shape != eps[n].shape:
                        raise TTError(
                            f"guide returned eps of shape {tuple(e.shape)} for {n!r}, expected {tuple(eps[n].shape)}"
                        )
                    eps[n] = torch.where(guided_masks[n].unsqueeze(-1), e, eps[n])
        if history is not None:
            history.append({n: v.detach() for n, v in x0.items()})
        with torch.set_grad_enabled(differentiable):
            for n in wanted:
                x_prev, _ = scheduler.step(keep(x[n]), keep(eps[n]), t, t_prev, eta=eta, generator=generator)
                x[n] = torch.where(updated[n].unsqueeze(-1), x_prev, keep(x[n]))
    for n, (m, x0_given) in given.items():
        x[n] = torch.where(m.unsqueeze(-1), x0_given, x[n])
    out = TokenBatch(
        {n: keep(x[n]).to(tokens.values[n].dtype) for n in layout.names}, dict(tokens.ids), dict(tokens.mask)
    )
    return SampleResult(out, updated, history)
