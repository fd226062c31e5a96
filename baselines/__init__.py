"""tt.baselines: Random and CMA-ES design optimizers behind one interface."""

from tt.baselines.cmaes import CMAES, CMAESConfig, CMAESPlan
from tt.baselines.evaluate import Evaluation, evaluate_designs, warm_up
from tt.baselines.problem import BACKENDS, Optimizer, Problem, Result, default_backend
from tt.baselines.random_search import RandomSearch

__all__ = [
    "BACKENDS",
    "CMAES",
    "CMAESConfig",
    "CMAESPlan",
    "Evaluation",
    "Optimizer",
    "Problem",
    "RandomSearch",
    "Result",
    "default_backend",
    "evaluate_designs",
    "warm_up",
]
