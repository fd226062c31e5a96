"""The draws of a RoboToken dataset: its config (`GenerateConfig`) and the seeded random
designs, augmented motions and episode filter that every episode comes from.

`tt generate` (`tt.generate`, the orchestration: shards, workers, CMA-ES biasing) and the
online training source (`tt.dit.online`) draw from here, so a dataset and an online run
of the same config see the same distribution. Every draw is a pure function of
``SeedSequence([seed, ...])`` (see `tt.generate` for the streams of a shard).
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, fields
from functools import lru_cache
from typing import Mapping

import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.tokens.schema import SCHEMA

#: Data biasing methods of ``--bias``.
BIASES = ("cmaes",)
#: Random streams of a shard (the third SeedSequence entry).
_STREAM_DESIGNS, _STREAM_EPISODES, _STREAM_CMAES, _STREAM_NOISE, _STREAM_SELECT = 0, 1, 2, 3, 4
#: Default control perturbation [rad or m] (measured, see the module docstring).
DEFAULT_ACTION_NOISE = 0.01


def default_action_noise(backend: str) -> float:
    """The control perturbation a dataset or online run gets when none is given:
    `DEFAULT_ACTION_NOISE` on "warp" (measured on ViperX), 0 elsewhere (quadruped datasets on
    "mjbatch" stay unperturbed unless asked)."""
    return DEFAULT_ACTION_NOISE if backend == "warp" else 0.0


#: Which robot count (`tt.tokens.tokenize.RobotIndex.counts`) sets each per-step type's tokens per step.
_STEP_COUNT = {
    "free_link_obs": "free_link",
    "track_link_obs": "track_link",
    "dyna_joint_obs": "dyna_joint",
    "ball_joint_obs": "ball_joint",
    "actuator_obs": "actuator",
    "control": "actuator",
    "target_pose": "track_link",
}
#: A quoted attribute value made of numbers only (MJCF numbers and vectors).
_NUMBERS = re.compile(r'"[-+0-9.eE ]*"')


#: The `tt generate` flag of each `GenerateConfig` field that has one (the others are its
#: --config keys; the Python API, `tt.api.generate_dataset`, takes the field's name as its
#: keyword argument).
FLAGS = {
    "space": "--space",
    "designs": "--designs",
    "episodes_per_design": "--episodes-per-design",
    "seed": "--seed",
}


def _named(field: str) -> str:
    """How an error names a `GenerateConfig` field: its `tt generate` flag and the keyword
    argument of the Python API ("--designs (designs=)"), or the argument alone for a field
    the command line does not set ("group_designs=")."""
    return f"{FLAGS[field]} ({field}=)" if field in FLAGS else f"{field}="


@dataclass(frozen=True)
class GenerateConfig:
    """What a dataset is; two runs with equal configs produce identical shards.

    space: design space name. designs: N designs in total. episodes_per_design: K episodes
    (motions) per design (paper: 10). seed: root of every random draw.
    designs_per_shard: designs per shard (the unit of resume and of distribution).
    group_designs: designs per rollout batch; a group shares its K augmented motions.
    bias: None (uniform designs) or "cmaes" (paper's data biasing).
    cmaes_popsize / cmaes_generations: CMA-ES population and generations per run (5, 3).
    min_steps: episodes with fewer executed control steps are dropped (paper: 100 = 2 s).
    max_motion_steps: cut training motions to this many steps (None: whole motions).
    max_yaw [rad], max_shift [m]: ranges of the per-episode planar motion augmentation.
    backend: rollout backend (`tt.sim.backends.BACKENDS`). reward: reward stored per
    episode and optimised by CMA-ES (`tt.sim.rewards.REWARDS`).
    action_noise: control perturbation, the standard deviation [rad or m] of the Gaussian
    noise on every executed command (clean commands are logged); 0: none (> 0 on the
    "warp" and "mjbatch" backends). CMA-ES biasing scores its candidates without it.
    select: designs screened per kept episode: each group keeps, per motion, the
    ``ceil(group / select)`` episodes `select_episodes` picks by `reward` (the best, and a
    `uniform_share` of them drawn uniformly), so every stored episode's design was chosen for
    that episode's motion; 1: every episode (no selection). `designs` counts the screen.
    """

    space: str
    designs: int
    episodes_per_design: int = 10
    seed: int = 0
    designs_per_shard: int = 1024
    group_designs: int = 128
    bias: str | None = None
    cmaes_popsize: int = 5
    cmaes_generations: int = 3
    min_steps: int = 100
    max_motion_steps: int | None = None
    max_yaw: float = math.pi / 8
    max_shift: float = 0.03
    backend: str = "warp"
    reward: str = "tracking"
    action_noise: float = DEFAULT_ACTION_NOISE
    select: int = 1
    uniform_share: float = 0.0

    def __post_init__(self) -> None:
        from tt.sim.backends import BACKENDS, get_backend
        from tt.sim.designs import get_space
        from tt.sim.rewards import REWARDS, reward_name

        get_space(self.space)  # raises listing the valid spaces
        for name in ("designs", "episodes_per_design", "designs_per_shard", "group_designs", "min_steps"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise TTError(f"{_named(name)} must be an integer >= 1, got {v!r}")
        if self.bias not in (None, *BIASES):
            raise TTError(
                f"{_named('bias')} must be one of {list(BIASES)} or left out (uniform designs), got {self.bias!r}"
            )
        if self.backend not in BACKENDS:
            raise TTError(f"{_named('backend')} must be one of {list(BACKENDS)}, got {self.backend!r}")
        if self.backend == "warp" and get_space(self.space).has_contacts:
            raise TTError(
                f"--space {self.space} (space={self.space!r}) has contacts; backend='warp' simulates "
                "contact-free trees only: give backend='mujoco'"
            )
        try:
            object.__setattr__(self, "reward", reward_name(self.reward))  # the paper's names too
        except TTError:
            raise TTError(f"{_named('reward')} must be one of {list(REWARDS)}, got {self.reward!r}") from None
        if self.max_motion_steps is not None and self.max_motion_steps < self.min_steps:
            raise TTError(
                f"{_named('max_motion_steps')} {self.max_motion_steps} is below {_named('min_steps')} "
                f"{self.min_steps}: every episode would be dropped"
            )
        if self.cmaes_popsize < 2 or self.cmaes_generations < 1:
            raise TTError(
                f"CMA-ES needs {_named('cmaes_popsize')} >= 2 and {_named('cmaes_generations')} >= 1, "
                f"got {self.cmaes_popsize} and {self.cmaes_generations}"
            )
        if not (0 <= self.max_yaw <= math.pi and 0 <= self.max_shift):
            raise TTError(
                f"the motion augmentation needs 0 <= {_named('max_yaw')} <= pi [rad] and "
                f"{_named('max_shift')} >= 0 [m], got {self.max_yaw} and {self.max_shift}"
            )
        if not 0 <= self.seed < 2**32:
            raise TTError(f"{_named('seed')} must be in 0..2**32-1, got {self.seed}")
        noise = self.action_noise
        if not (isinstance(noise, (int, float, np.integer, np.floating)) and math.isfinite(noise) and noise >= 0):
            raise TTError(
                f"{_named('action_noise')} must be a finite standard deviation >= 0 [rad or m], got {noise!r}"
            )
        check_selection(self.select, self.uniform_share, _named("select"), _named("uniform_share"))
        perturbing = [name for name in BACKENDS if get_backend(name).perturbs]
        if self.action_noise > 0 and self.backend not in perturbing:
            raise TTError(
                f"{_named('action_noise')} {self.action_noise} needs backend {' or '.join(map(repr, perturbing))}, "
                f"the ones that perturb commands; backend {self.backend!r} runs the clean ones: give 0"
            )

    @property
    def shards(self) -> int:
        return -(-self.designs // self.designs_per_shard)

    def shard_designs(self, index: int) -> int:
        """Number of designs of shard `index`."""
        if not 0 <= index < self.shards:
            raise TTError(f"shard {index} does not exist; the dataset has shards 0..{self.shards - 1}")
        return min(self.designs_per_shard, self.designs - index * self.designs_per_shard)

    def group_keep(self, group: int) -> int:
        """Episodes a group of `group` designs keeps per motion under selection."""
        return -(-group // self.select)

    def to_dict(self) -> dict:
        d = asdict(self)
        if self.select == 1 and self.uniform_share == 0.0:
            # Unselected datasets keep the root they had before selection existed.
            del d["select"], d["uniform_share"]
        return {**d, "shards": self.shards}

    @staticmethod
    def from_dict(d: Mapping) -> "GenerateConfig":
        names = {f.name for f in fields(GenerateConfig)}
        return GenerateConfig(**{k: v for k, v in d.items() if k in names})


def _seed_seq(*entropy: int) -> np.random.SeedSequence:
    return np.random.SeedSequence([int(e) for e in entropy])


def _rng(*entropy: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(_seed_seq(*entropy)))


def _seed_int(*entropy: int, bits: int = 31) -> int:
    return int(_seed_seq(*entropy).generate_state(1, np.uint64)[0] >> np.uint64(64 - bits))


# ------------------------------------------------------------------------------ space maxima
def _discrete_choices(space, limit: int) -> list[tuple[int, ...]] | None:
    """Every complete discrete choice of `space`, or None if there are more than `limit`."""
    out: list[tuple[int, ...]] = []
    stack: list[tuple[int, ...]] = [()]
    while stack:
        prefix = stack.pop()
        params = space.discrete_params(list(prefix))
        if len(prefix) == len(params):
            out.append(prefix)
            if len(out) > limit:
                return None
            continue
        stack += [prefix + (i,) for i in reversed(range(len(params[len(prefix)].options)))]
    return out


@lru_cache(maxsize=8)
def space_token_maxima(space_name: str, limit: int = 4096) -> dict:
    """Largest token counts of a design space's robots: tokens per robot of each embodiment
    type, tokens per control step of each per-step type; and the widest design.

    Token counts depend on the discrete choices only, so every discrete choice is considered
    (continuous choices at mid-range) when there are at most `limit`; otherwise `limit`
    random designs are (``source`` says which). Counts depend on the MJCF element tree, not
    on numbers, so one model per distinct tree (MJCF text with numeric attribute values
    blanked) is compiled and tokenized. Returns {"maxima": {type: count}, "discrete": max
    discrete choices, "continuous": max continuous choices, "source": str}.
    """
    import mujoco

    from tt.sim.designs import Design, get_space
    from tt.tokens.tokenize import Tokenizer

    sp = get_space(space_name)
    choices = _discrete_choices(sp, limit)
    if choices is None:
        designs = sp.sample(limit, seed=0)
        source = f"{limit} random designs"
    else:
        designs = [Design(sp.name, c, tuple(0.5 * (p.low + p.high) for p in sp.continuous_params(c))) for c in choices]
        source = f"all {len(choices)} discrete choices"
    trees: dict[str, str] = {}
    for d in designs:
        text = sp.to_mjcf(d)
        trees.setdefault(_NUMBERS.sub('""', text), text)
    tokenizer = Tokenizer()
    maxima = {n: 0 for n in SCHEMA.names()}
    texts = list(trees.values())
    for start in range(0, len(texts), 512):
        emb = tokenizer([mujoco.MjModel.from_xml_string(t) for t in texts[start : start + 512]])
        for name, c in emb.tokens.counts().items():
            maxima[name] = max(maxima[name], int(c.max()))
        for r in emb.index:
            for name, key in _STEP_COUNT.items():
                maxima[name] = max(maxima[name], int(r.counts[key]))
    return {
        "maxima": maxima,
        "discrete": max(len(d.discrete) for d in designs),
        "continuous": max(len(d.continuous) for d in designs),
        "source": source,
    }


# ------------------------------------------------------------------------------ motions
@lru_cache(maxsize=8)
def training_motions(space_name: str) -> tuple:
    """The training split's library motions for the space's end-effector count (unplaced:
    `for_space` is applied after augmentation)."""
    from tt.sim.designs import get_space
    from tt.sim.motions import motion_set

    return tuple(motion_set("train", arms=get_space(space_name).ee_count))


def episode_motion(config: GenerateConfig, base, aug_seed: int):
    """Augmented, placed and (optionally) cut training motion."""
    from tt.sim.motions import augment_motion, for_space
    from tt.sim.motions.base import Motion

    m = augment_motion(base, int(aug_seed), max_yaw=config.max_yaw, max_shift=config.max_shift)
    m = for_space([m], config.space)[0]
    if config.max_motion_steps is not None and m.steps > config.max_motion_steps:
        n = config.max_motion_steps
        m = Motion(m.name, m.pos[:n], m.quat[:n], m.dt, meta=dict(m.meta, cut=n))
    return m


def finite_worlds(ep) -> np.ndarray:
    """(W,) True where every executed step's state, command and pose is finite."""
    alive = ep.alive.bool()
    ok = torch.ones(ep.worlds, dtype=torch.bool, device=alive.device)
    for name in ("qpos", "qvel", "ctrl", "action", "act_force", "act_vel", "ee_pos", "ee_quat"):
        x = getattr(ep, name)
        bad = ~torch.isfinite(x).reshape(x.shape[0], x.shape[1], -1).all(-1)
        ok &= ~(bad & alive).any(1)
    return ok.cpu().numpy()


# ------------------------------------------------------------------------------ motion-selected episodes
def check_selection(select, uniform_share: float, select_flag: str, share_flag: str) -> None:
    """Refuse a selection setting (`GenerateConfig`, `tt.dit.online.OnlineConfig`), naming the
    flags: `select` an integer >= 1, `uniform_share` in [0, 1] and only with `select` above 1."""
    if not (isinstance(select, (int, np.integer)) and select >= 1):
        raise TTError(f"{select_flag} must be an integer >= 1 (designs screened per kept episode), got {select!r}")
    if not 0.0 <= uniform_share <= 1.0:
        raise TTError(f"{share_flag} must lie in [0, 1], got {uniform_share}")
    if uniform_share > 0 and select == 1:
        raise TTError(
            f"{share_flag} applies only with {select_flag} above 1 (without selection every design is uniform)"
        )


def select_episodes(
    reward: np.ndarray,
    motion: np.ndarray,
    eligible: np.ndarray,
    keep: int,
    uniform_share: float,
    rng: np.random.Generator | None,
) -> np.ndarray:
    """Which screened episodes a dataset keeps so that each design was chosen for its motion.

    Every design of a screen runs every motion; per motion, the `keep` eligible episodes are
    its ``keep - round(keep * uniform_share)`` best by `reward` (ties to the lower world
    index) and ``round(keep * uniform_share)`` drawn uniformly from the other eligible ones,
    so a model trained on them still sees designs that fail. Without selection the data pairs
    a uniform design with an independent motion, and motion-to-robot learns p(design), the
    prior (issue 51).

    reward: (W,) float, each world's reward on its own motion; motion: (W,) int, its motion;
    eligible: (W,) bool, worlds the filters kept (finite, long enough). rng: the uniform
    share's draws (unused when it is 0). Returns (W,) bool.
    """
    reward = np.asarray(reward, np.float64)
    motion = np.asarray(motion)
    eligible = np.asarray(eligible, bool)
    if not 0.0 <= uniform_share <= 1.0:
        raise TTError(f"uniform share {uniform_share} must lie in [0, 1]")
    n_uniform = int(round(keep * uniform_share))
    out = np.zeros(len(reward), bool)
    for m in np.unique(motion):
        idx = np.nonzero((motion == m) & eligible)[0]
        # lexsort: the last key is primary; stable on the world index for equal rewards.
        order = idx[np.lexsort((idx, -np.nan_to_num(reward[idx], nan=-np.inf)))]
        top = order[: max(keep - n_uniform, 0)]
        out[top] = True
        rest = order[len(top) :]
        if n_uniform and len(rest):
            out[rng.choice(rest, size=min(n_uniform, len(rest)), replace=False)] = True
    return out
