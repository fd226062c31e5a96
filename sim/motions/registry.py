"""The motion library by name: `get_motion("toss")`, `get_motion("toss:7")`, the fixed
splits `motion_set("train" | "val", arms=...)`, `list_motions()` for ``tt motions``, and
one function per skill (``toss(seed, **params)``). The skills themselves are in
`tt.sim.motions.skills`.
"""

from __future__ import annotations

from dataclasses import dataclass

from tt.sim.motions.base import Motion, MotionError
from tt.sim.motions.skills import (
    BI_FLING,
    BI_FOLD,
    BI_HANDOVER,
    BI_JAR,
    BI_LIFT,
    DRAWER_OPEN,
    FLING,
    HAMMER,
    POUR,
    REACH_PLACE,
    SCREW,
    SCRUB,
    SPLITS,
    STIR,
    TOSS,
    TRAIN_SEEDS,
    VAL_SEEDS,
    WIPE,
    Skill,
)

#: Every skill by name, single-arm first.
SKILLS: dict[str, Skill] = {
    s.name: s
    for s in (
        TOSS,
        SCRUB,
        DRAWER_OPEN,
        SCREW,
        WIPE,
        POUR,
        REACH_PLACE,
        FLING,
        STIR,
        HAMMER,
        BI_FLING,
        BI_LIFT,
        BI_HANDOVER,
        BI_FOLD,
        BI_JAR,
    )
}


def toss(seed: int = 0, **params: float) -> Motion:
    """Underhand toss (parameters: `TOSS.params`)."""
    return TOSS.motion(seed, **params)


def scrub(seed: int = 0, **params: float) -> Motion:
    """Table scrub (parameters: `SCRUB.params`)."""
    return SCRUB.motion(seed, **params)


def drawer_open(seed: int = 0, **params: float) -> Motion:
    """Open a drawer (parameters: `DRAWER_OPEN.params`)."""
    return DRAWER_OPEN.motion(seed, **params)


def screw(seed: int = 0, **params: float) -> Motion:
    """Ratchet screwing about the approach axis (parameters: `SCREW.params`)."""
    return SCREW.motion(seed, **params)


def wipe(seed: int = 0, **params: float) -> Motion:
    """Wipe a vertical surface (parameters: `WIPE.params`)."""
    return WIPE.motion(seed, **params)


def pour(seed: int = 0, **params: float) -> Motion:
    """Pour from a held cup (parameters: `POUR.params`)."""
    return POUR.motion(seed, **params)


def reach_place(seed: int = 0, **params: float) -> Motion:
    """Pick and place (parameters: `REACH_PLACE.params`)."""
    return REACH_PLACE.motion(seed, **params)


def fling(seed: int = 0, **params: float) -> Motion:
    """One-arm cloth fling (parameters: `FLING.params`)."""
    return FLING.motion(seed, **params)


def stir(seed: int = 0, **params: float) -> Motion:
    """Stir a pot (parameters: `STIR.params`)."""
    return STIR.motion(seed, **params)


def hammer(seed: int = 0, **params: float) -> Motion:
    """Hammer a nail (parameters: `HAMMER.params`)."""
    return HAMMER.motion(seed, **params)


def bi_fling(seed: int = 0, **params: float) -> Motion:
    """Two-arm cloth fling (parameters: `BI_FLING.params`)."""
    return BI_FLING.motion(seed, **params)


def bi_lift(seed: int = 0, **params: float) -> Motion:
    """Two-arm box lift (parameters: `BI_LIFT.params`)."""
    return BI_LIFT.motion(seed, **params)


def bi_handover(seed: int = 0, **params: float) -> Motion:
    """Handover between the arms (parameters: `BI_HANDOVER.params`)."""
    return BI_HANDOVER.motion(seed, **params)


def bi_fold(seed: int = 0, **params: float) -> Motion:
    """Two-arm cloth fold (parameters: `BI_FOLD.params`)."""
    return BI_FOLD.motion(seed, **params)


def bi_jar(seed: int = 0, **params: float) -> Motion:
    """Open a jar with two arms (parameters: `BI_JAR.params`)."""
    return BI_JAR.motion(seed, **params)


def _seed_ranges(seeds: tuple[int, ...]) -> str:
    return f"{seeds[0]}-{seeds[-1]}" if seeds == tuple(range(seeds[0], seeds[-1] + 1)) else ",".join(map(str, seeds))


@dataclass(frozen=True)
class MotionInfo:
    """One row of `list_motions`: a skill, its canonical motion's size, and its split seeds."""

    name: str
    arms: int
    duration: float
    steps: int
    params: tuple[str, ...]
    train_seeds: tuple[int, ...]
    val_seeds: tuple[int, ...]
    summary: str

    def row(self) -> dict[str, str | int | float]:
        """Flat, printable columns: name, arms, duration_s, steps, train, val, params, summary."""
        return {
            "name": self.name,
            "arms": self.arms,
            "duration_s": round(self.duration, 2),
            "steps": self.steps,
            "train": f"seeds {_seed_ranges(self.train_seeds)}",
            "val": f"seeds {_seed_ranges(self.val_seeds)}",
            "params": ", ".join(self.params),
            "summary": self.summary,
        }


def list_motions(arms: int | None = None) -> list[MotionInfo]:
    """Every library skill (or those with `arms` end effectors), single-arm first."""
    if arms not in (None, 1, 2):
        raise MotionError(f"arms must be 1, 2 or None, got {arms!r}")
    out = []
    for sk in SKILLS.values():
        if arms is not None and sk.arms != arms:
            continue
        m = sk.motion(0)
        out.append(
            MotionInfo(
                sk.name,
                sk.arms,
                m.duration,
                m.steps,
                tuple(p.name for p in sk.params),
                TRAIN_SEEDS,
                VAL_SEEDS,
                sk.summary,
            )
        )
    return out


def get_motion(name: str, seed: int | None = None) -> Motion:
    """The library motion `name` with `seed` (default 0, the canonical one).

    `name` may carry its seed as ``"toss:7"``; raises `MotionError` listing the valid
    names for an unknown one. The motion's ``meta`` holds skill, seed, split and params.
    """
    skill, sep, tail = str(name).partition(":")
    if sep:
        try:
            named_seed = int(tail)
        except ValueError:
            raise MotionError(f"motion {name!r}: the part after ':' must be an integer seed") from None
        if seed is not None and seed != named_seed:
            raise MotionError(f"motion {name!r} names seed {named_seed} but seed={seed} was passed")
        seed = named_seed
    if skill not in SKILLS:
        raise MotionError(f"unknown motion {skill!r}; valid: {', '.join(SKILLS)}")
    return SKILLS[skill].motion(0 if seed is None else seed)


#: The motion a command runs when none is named, by end-effector count: the toss for one arm,
#: the bimanual fling for two.
DEFAULT_MOTIONS = {1: "toss", 2: "bi_fling"}


def default_motion(arms: int) -> str:
    """Name of the motion to run for a robot with `arms` end effectors when none is named."""
    if arms not in DEFAULT_MOTIONS:
        raise MotionError(f"no library motion for {arms} end effectors; the library has {sorted(DEFAULT_MOTIONS)}")
    return DEFAULT_MOTIONS[arms]


def motion_set(split: str, arms: int | None = None) -> list[Motion]:
    """All motions of a split: every skill (with `arms` end effectors, or all) at every split seed.

    train: seeds `TRAIN_SEEDS` of every skill; val: seeds `VAL_SEEDS`. Ordered by skill
    (as in `SKILLS`), then seed; the same call always returns the same motions.
    """
    if split not in SPLITS:
        raise MotionError(f"unknown split {split!r}; valid: {list(SPLITS)}")
    if arms not in (None, 1, 2):
        raise MotionError(f"arms must be 1, 2 or None, got {arms!r}")
    return [get_motion(sk.name, seed) for sk in SKILLS.values() if arms in (None, sk.arms) for seed in SPLITS[split]]


__all__ = [
    "DEFAULT_MOTIONS",
    "SKILLS",
    "MotionInfo",
    "bi_fling",
    "bi_fold",
    "bi_handover",
    "bi_jar",
    "bi_lift",
    "default_motion",
    "drawer_open",
    "fling",
    "get_motion",
    "hammer",
    "list_motions",
    "motion_set",
    "pour",
    "reach_place",
    "screw",
    "scrub",
    "stir",
    "toss",
    "wipe",
]
