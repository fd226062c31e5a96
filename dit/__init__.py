"""tt.dit: the diffusion transformer over RoboTokens, its DDIM scheduler, tasks, training and checkpoints."""

from tt.dit.checkpoint import TrainedModel, load_checkpoint, load_model
from tt.dit.data import EpisodeTokens
from tt.dit.ddim import CosineDDIM
from tt.dit.ema import EMA
from tt.dit.layout import Layout, LayoutError, TokenSpec, layout_from_schema
from tt.dit.model import DIT_CONFIGS, DiTConfig, RoboDiT, get_config
from tt.dit.sampling import GuideFn, SampleResult, sample
from tt.dit.tasks import CONTROL, ROBOT, TaskMasks, TaskSpec, get_task, task_masks
from tt.dit.train import TrainConfig, TrainResult, train
from tt.tokens.normalize import Normalizer

__all__ = [
    "CONTROL",
    "DIT_CONFIGS",
    "EMA",
    "ROBOT",
    "CosineDDIM",
    "DiTConfig",
    "EpisodeTokens",
    "GuideFn",
    "Layout",
    "LayoutError",
    "Normalizer",
    "RoboDiT",
    "SampleResult",
    "TaskMasks",
    "TaskSpec",
    "TokenSpec",
    "TrainConfig",
    "TrainResult",
    "TrainedModel",
    "get_config",
    "get_task",
    "layout_from_schema",
    "load_checkpoint",
    "load_model",
    "sample",
    "task_masks",
    "train",
]
