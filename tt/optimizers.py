"""The optimizer registry: every design optimizer of tt by name, behind one interface.

`tt optimize --method` and `tt demo` pick optimizers here. It sits in the app layer because
it names optimizers of two layers: the baselines (`tt.baselines`: Random, CMA-ES) and the
learned samplers of `tt.guidance` (Zeroth-Order, Dynamics Self-Guidance).
"""

from __future__ import annotations

from tt.baselines import CMAES, CMAESConfig, Optimizer, RandomSearch

#: Optimizer names accepted by `get_optimizer` and `tt optimize --method`; zeroth and dgs
#: are the learned samplers of `tt.guidance`, behind the same interface; zeroth-sim,
#: dgs-sim and cmaes-init-model (`tt optimize --method cmaes --init model`) are the hybrids
#: of `tt.guidance.hybrid`, which verify the model's proposals in the batched simulator.
METHODS = ("random", "cmaes", "zeroth", "dgs", "zeroth-sim", "dgs-sim", "cmaes-init-model")
#: The methods that need a trained model (a checkpoint).
LEARNED = ("zeroth", "dgs", "zeroth-sim", "dgs-sim", "cmaes-init-model")


def get_optimizer(method: str, **options) -> Optimizer:
    """An optimizer by name; options go to its config (e.g. popsize=8 for cmaes)."""
    if method == "random":
        if options:
            raise ValueError(f"random search takes no options, got {sorted(options)}")
        return RandomSearch()
    if method == "cmaes":
        from dataclasses import fields

        unknown = sorted(set(options) - {f.name for f in fields(CMAESConfig)})
        if unknown:
            raise ValueError(f"unknown cmaes options {unknown}; valid: {[f.name for f in fields(CMAESConfig)]}")
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
        return ModelInitCMAES(ZerothOrder(SamplerConfig(**{k: v for k, v in options.items() if k not in cma_names})),
                              CMAESConfig(**cma))
    raise ValueError(f"unknown method {method!r}; valid: {list(METHODS)}")
