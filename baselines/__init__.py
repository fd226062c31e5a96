"""tt.baselines: Random and CMA-ES design optimizers behind one interface."""

from tt.baselines.cmaes import CMAES, CMAESConfig
from tt.baselines.evaluate import Evaluation, evaluate_designs
from tt.baselines.problem import BACKENDS, Optimizer, Problem, Result
from tt.baselines.random_search import RandomSearch

#: Optimizer names accepted by `get_optimizer` and `tt optimize --method`.
METHODS = ("random", "cmaes")


def get_optimizer(method: str, **options) -> Optimizer:
    """An optimizer by name; options go to its config (e.g. popsize=8 for cmaes)."""
    if method == "random":
        if options:
            raise ValueError(f"random search takes no options, got {sorted(options)}")
        return RandomSearch()
    if method == "cmaes":
        return CMAES(CMAESConfig(**options))
    raise ValueError(f"unknown method {method!r}; valid: {list(METHODS)}")


__all__ = [
    "BACKENDS", "CMAES", "CMAESConfig", "Evaluation", "METHODS", "Optimizer", "Problem", "RandomSearch",
    "Result", "evaluate_designs", "get_optimizer",
]
