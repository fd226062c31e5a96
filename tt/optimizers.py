"""The optimizer registry: every design optimizer of tt by name, behind one interface.

`tt optimize --method` and `tt demo` pick optimizers here. It sits in the app layer because
it names optimizers of two layers: the baselines (`tt.baselines`: Random, CMA-ES) and the
learned samplers of `tt.guidance` (Zeroth-Order, Dynamics Self-Guidance).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the baselines load with the first optimizer, so `tt.api` and the CLI import this module fast
    from tt.baselines import Optimizer, Problem, Result

#: Optimizer names accepted by `get_optimizer` and `tt optimize --method`; zeroth and dgs
#: are the learned samplers of `tt.guidance`, behind the same interface; zeroth-sim,
#: dgs-sim and cmaes-init-model (`tt optimize --method cmaes --init model`) are the hybrids
#: of `tt.guidance.hybrid`, which verify the model's proposals in the batched simulator.
METHODS = ("random", "cmaes", "zeroth", "dgs", "zeroth-sim", "dgs-sim", "cmaes-init-model")
#: The methods that need a trained model (a checkpoint).
LEARNED = ("zeroth", "dgs", "zeroth-sim", "dgs-sim", "cmaes-init-model")


#: The methods that rank their samples with a critic (all learned ones but cmaes-init-model,
#: which ranks by simulating them).
RANKED = ("zeroth", "dgs", "zeroth-sim", "dgs-sim")


def learned_defaults(method: str, space: str, options: dict) -> dict:
    """`options` with the learned methods' defaults for design space `space` filled in, the
    one definition `tt optimize` and `tt.optimize` share:

    - ``checkpoint`` None: the space's shipped generator (`tt.dit.checkpoint.default_checkpoint`
      with task "robot"; an error naming the spaces that ship one if `space` has none);
    - ``critic_checkpoint`` None, for a method that ranks samples (`RANKED`) unless
      ``critic="joint"`` or ``critic_on="tokens"``: the space's shipped dynamics critic when
      ``checkpoint`` is the shipped model (`tt.dit.checkpoint.shipped_critic`; it ranks far
      better than the generalist's own dynamics task, 9 of 9 seeds against 5 of 9:
      benchmarks/results/zeroth_ranking_start_critic.md, zeroth_ranking.md), else none (the
      sampling model's own dynamics task).

    Other methods' options are returned unchanged."""
    if method not in LEARNED:
        return dict(options)
    out = dict(options)
    if out.get("checkpoint") is None:
        from tt.dit.checkpoint import default_checkpoint

        out["checkpoint"] = str(default_checkpoint(space, task="robot"))
    if (
        out.get("critic_checkpoint") is None
        and method in RANKED
        and out.get("critic") != "joint"
        and out.get("critic_on") != "tokens"
    ):
        from tt.dit.checkpoint import shipped_critic

        critic = shipped_critic(space, out["checkpoint"])
        out["critic_checkpoint"] = None if critic is None else str(critic)
    for key in ("checkpoint", "critic_checkpoint"):
        if isinstance(out.get(key), Path):
            out[key] = str(out[key])
    if out.get("critic_checkpoint") is None:
        out.pop("critic_checkpoint", None)
    return out


def method_keys(method: str) -> dict[str, str]:
    """The options `get_optimizer(method, ...)` takes (`tt optimize --config`'s keys): each
    field of the method's config(s) and its type annotation text (`tt.baselines.CMAESConfig`,
    `tt.guidance.zeroth.SamplerConfig`, `tt.guidance.selfguide.DGSConfig`, and ``verify`` for
    the -sim hybrids); none for random."""
    from dataclasses import fields

    from tt.baselines import CMAESConfig
    from tt.kernels.errors import TTError

    if method not in METHODS:
        raise TTError(f"unknown method {method!r}; valid: {list(METHODS)}")
    configs = []
    if method in ("cmaes", "cmaes-init-model"):
        configs.append(CMAESConfig)
    if method in ("zeroth", "zeroth-sim", "cmaes-init-model"):
        from tt.guidance.zeroth import SamplerConfig

        configs.append(SamplerConfig)
    if method in ("dgs", "dgs-sim"):
        from tt.guidance.selfguide import DGSConfig

        configs.append(DGSConfig)
    keys = {f.name: str(f.type) for c in configs for f in fields(c)}
    if method.endswith("-sim"):
        keys["verify"] = "int | None"
    return keys


def get_optimizer(method: str, *, space: str | None = None, **options) -> Optimizer:
    """An optimizer by name; options go to its config (e.g. popsize=8 for cmaes).

    space: the design space it will optimize; with it, a learned method's checkpoint and
    critic default to the space's shipped ones (`learned_defaults`), as in `tt optimize`.
    Without it a learned method needs ``checkpoint=`` and ranks by that model's own dynamics
    unless ``critic_checkpoint=`` is given."""
    from tt.baselines import CMAES, CMAESConfig, RandomSearch
    from tt.kernels.errors import TTError

    if space is not None:
        options = learned_defaults(method, space, options)
    if method == "random":
        if options:
            raise TTError(f"random search takes no options, got {sorted(options)}")
        return RandomSearch()
    if method == "cmaes":
        from dataclasses import fields

        unknown = sorted(set(options) - {f.name for f in fields(CMAESConfig)})
        if unknown:
            raise TTError(f"unknown cmaes options {unknown}; valid: {[f.name for f in fields(CMAESConfig)]}")
        return CMAES(CMAESConfig(**options))
    if method == "zeroth":
        from tt.guidance.zeroth import SamplerConfig, ZerothOrder  # lazy: torch models load only when asked for

        return ZerothOrder(SamplerConfig(**options))
    if method == "dgs":
        from tt.guidance.selfguide import DGSConfig, DynamicsSelfGuidance

        return DynamicsSelfGuidance(DGSConfig(**options))
    if method in ("zeroth-sim", "dgs-sim"):
        from tt.guidance.hybrid import SimVerified, VerifyConfig

        verify = options.pop("verify", None)
        return SimVerified(get_optimizer(method.removesuffix("-sim"), **options), VerifyConfig(verify))
    if method == "cmaes-init-model":
        from dataclasses import fields

        from tt.guidance.hybrid import ModelInitCMAES
        from tt.guidance.zeroth import SamplerConfig, ZerothOrder

        cma_names = {f.name for f in fields(CMAESConfig)}
        cma = {k: v for k, v in options.items() if k in cma_names}
        return ModelInitCMAES(
            ZerothOrder(SamplerConfig(**{k: v for k, v in options.items() if k not in cma_names})), CMAESConfig(**cma)
        )
    raise TTError(f"unknown method {method!r}; valid: {list(METHODS)}")


def run_optimizer(problem: Problem, method: str = "cmaes", **options) -> Result:
    """Optimize `problem` with the optimizer `method` (`get_optimizer`, the learned defaults of
    the problem's space filled in); a CMA-ES budget below one population fails before any
    work. What `tt optimize` and `tt.optimize` run."""
    opt = get_optimizer(method, space=problem.space, **options)
    if method == "cmaes":
        opt.plan(problem)
    if method == "cmaes-init-model":
        opt.cmaes.plan(problem)
    return opt.optimize(problem)
