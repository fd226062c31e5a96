"""RoboTokens: the schema, tokenizer and detokenizer for rigid articulated robots, episode
tokens and their normalisation for diffusion.

    emb = tokenize_models([space.model(d) for d in designs])       # embodiment tokens
    dyn = episode_tokens(episode, emb.index, steps=8, mode="random")  # dynamics + targets
    norm = Normalizer.fit(batches); x = norm.normalize(emb.tokens)    # [-1, 1]
    results = detokenize(norm.denormalize(x_hat, detect_padding=True))  # MJCF + MjModel

Tokens travel as one container, `TokenBatch` (numpy or torch); `Role` and `PAD_VALUE`
are defined once, in `schema`. Datasets on disk: `store` (shards), `lock`, `info`.
"""

from tt.tokens.batch import TokenBatch
from tt.tokens.design_fit import CandidateTable, DesignFit, design_from_tokens
from tt.tokens.detokenize import DetokenizeConfig, DetokenizeResult, decode_robot, detokenize, robot_to_mjcf
from tt.tokens.episodes import episode_tokens, sample_steps
from tt.tokens.normalize import Normalizer, is_padding
from tt.tokens.roundtrip import RoundTripReport, compare_models
from tt.tokens.schema import PAD_VALUE, SCHEMA, SCHEMA_VERSION, Encoding, Role, SchemaVersionError, TokenType
from tt.tokens.tokenize import (
    Embodiments,
    RobotIndex,
    TokenizeConfig,
    TokenizeError,
    Tokenizer,
    TokenizeWarning,
    tokenize_model,
    tokenize_models,
)

__all__ = [
    "CandidateTable",
    "DesignFit",
    "DetokenizeConfig",
    "DetokenizeResult",
    "Embodiments",
    "Encoding",
    "Normalizer",
    "PAD_VALUE",
    "RobotIndex",
    "Role",
    "RoundTripReport",
    "SCHEMA",
    "SCHEMA_VERSION",
    "SchemaVersionError",
    "TokenBatch",
    "TokenType",
    "TokenizeConfig",
    "TokenizeError",
    "TokenizeWarning",
    "Tokenizer",
    "compare_models",
    "decode_robot",
    "design_from_tokens",
    "detokenize",
    "episode_tokens",
    "is_padding",
    "robot_to_mjcf",
    "sample_steps",
    "tokenize_model",
    "tokenize_models",
]
