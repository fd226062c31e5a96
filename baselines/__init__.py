"""tt.baselines: Random and CMA-ES design optimizers behind one interface."""

from tt.baselines.cmaes import CMAES, CMAESConfig, CMAESPlan
from tt.baselines.evaluate import Evaluation, evaluate_designs, warm_up
from tt.baselines.problem import BACKENDS, Optimizer, Problem, Result, default_backend
from tt.baselines.random_search import RandomSearch

#: Optimizer names accepted by `get_optimizer` and `tt optimize --method`; zeroth and dgs
#: are the learned samplers of `tt.guidance`, behind the same interface.
METHODS = ("random", "cmaes", "zeroth", "dgs")


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
        from tt.guidance.zeroth import SamplerConfig, ZerothOrder  # lazy: guidance imports baselines

        return ZerothOrder(SamplerConfig(**options))
    if method == "dgs":
        from tt.guidance.selfguide import DGSConfig, DynamicsSelfGuidance

        return DynamicsSelfGuidance(DGSConfig(**options))
    raise ValueError(f"unknown method {method!r}; valid: {list(METHODS)}")


__all__ = [
    "BACKENDS", "CMAES", "CMAESConfig", "CMAESPlan", "Evaluation", "METHODS", "Optimizer", "Problem",
    "RandomSearch", "Result", "default_backend", "evaluate_designs", "get_optimizer", "warm_up",
]
