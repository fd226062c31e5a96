"""The rollout-backend interface and the one design -> model resolver.

Every batched rollout in tt starts the same way: D designs (tt `Design`s of one design
space, or compiled `mujoco.MjModel`s with end-effector sites ``ee_0``, ...) become the
compiled models a simulator runs. `resolve_designs` is the only function that does that;
a backend states what it cannot run (contacts, several design spaces in one call) and the
resolver raises the error that names the design. `RolloutBackend` is what every backend
implements: its own `resolve` (the resolver with its constraints) and `run`, which rolls
the resolved robots along M motions into one `tt.sim.episode.Episode` of W = D * M
worlds, design-major. The registry by name is `tt.sim.backends`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence, runtime_checkable

import mujoco

from tt.kernels.errors import TTError
from tt.sim.controller import IKConfig, ee_site_names, model_name
from tt.sim.designs import Design, get_space
from tt.sim.episode import Episode
from tt.sim.motions.base import Motion


@dataclass(frozen=True)
class Robots:
    """D designs resolved for simulation.

    models: the compiled models, one per design, in input order.
    sites: end-effector site names of each model (``ee_0``, ...).
    mjcf: the MJCF text of each model, None where the input was an `MjModel` (a compiled
        model does not carry its MJCF; backends that import MJCF need Designs).
    """

    models: tuple[mujoco.MjModel, ...]
    sites: tuple[tuple[str, ...], ...]
    mjcf: tuple[str | None, ...]

    def __len__(self) -> int:
        return len(self.models)

    @property
    def ee_sites(self) -> tuple[str, ...]:
        """The end-effector sites every model shares; raises ValueError naming the first
        design whose sites differ from designs[0]'s."""
        first = self.sites[0]
        for i, s in enumerate(self.sites):
            if s != first:
                raise TTError(
                    f"designs[{i}] ({model_name(self.models[i])!r}) has end effectors {list(s)}, "
                    f"designs[0] has {list(first)}"
                )
        return first


def check_designs(
    designs: Sequence[Design | mujoco.MjModel],
    *,
    who: str = "a rollout",
    one_space: bool = True,
    contacts: bool = True,
    hint: str = "",
) -> None:
    """The checks of `resolve_designs` that need no compiled model (arguments as there)."""
    if len(designs) == 0:
        raise TTError(f"designs is empty; {who} needs at least one design")
    for i, d in enumerate(designs):
        if not isinstance(d, (Design, mujoco.MjModel)):
            raise TypeError(f"designs[{i}] is a {type(d).__name__}; expected a tt Design or a mujoco.MjModel")
    spaces = sorted({d.space for d in designs if isinstance(d, Design)})
    if one_space:
        if len(spaces) > 1:
            raise TTError(
                f"designs mix design spaces {spaces}; roll out one design space per call "
                "(motions and rewards are per space)"
            )
        if spaces and any(isinstance(d, mujoco.MjModel) for d in designs):
            raise TTError("designs mix tt Designs and raw MjModels; pass one kind per call")
    if not contacts:
        for name in spaces:
            if get_space(name).has_contacts:
                raise TTError(
                    f"design space {name!r} has contacts (has_contacts=True); {who} simulates "
                    f"contact-free trees only{'; ' + hint if hint else ''}"
                )


def resolve_designs(
    designs: Sequence[Design | mujoco.MjModel],
    *,
    who: str = "a rollout",
    one_space: bool = True,
    contacts: bool = True,
    hint: str = "",
) -> Robots:
    """Compile D designs into `Robots`.

    designs: tt Designs and/or mujoco.MjModels (MjModels need sites ``ee_0``, ...).
    who: what needs the models, for error messages ("the 'warp' backend").
    one_space: require one kind per call, tt Designs of one design space or MjModels (the
        batched backends: motions and rewards are per space); False lets the oracle run
        any mix, world by world.
    contacts: False raises for a design space with contacts (``has_contacts``).
    hint: what to do instead, appended to that error ("use backend='mjwarp' or 'mujoco'").
    Raises ValueError (TypeError for an input of another type) naming the design.
    """
    check_designs(designs, who=who, one_space=one_space, contacts=contacts, hint=hint)
    models, sites, mjcf = [], [], []
    for i, d in enumerate(designs):
        if isinstance(d, Design):
            space = get_space(d.space)
            xml = space.to_mjcf(d)
            model = mujoco.MjModel.from_xml_string(xml)  # what DesignSpace.model does, keeping the text
            s = space.ee_sites()
            for site in s:
                if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site) < 0:
                    raise TTError(f"designs[{i}] of space {d.space!r} has no site {site!r}")
        else:
            model, s, xml = d, ee_site_names(d), None
        models.append(model)
        sites.append(s)
        mjcf.append(xml)
    return Robots(tuple(models), tuple(sites), tuple(mjcf))


def check_motions(motions: Sequence[Motion], control_dt: float, arms: int) -> None:
    """Raise ValueError unless the M motions are tt Motions sampled at `control_dt` [s]
    with `arms` end effectors each (TypeError for another type)."""
    if len(motions) == 0:
        raise TTError("motions is empty; rollout needs at least one motion")
    for m, motion in enumerate(motions):
        if not isinstance(motion, Motion):
            raise TypeError(f"motions[{m}] is a {type(motion).__name__}; expected tt.sim.motions.base.Motion")
    dts = sorted({float(motion.dt) for motion in motions})
    if len(dts) > 1:
        raise TTError(f"motions have different dt {dts} s; resample them to one rate (tt uses 50 Hz)")
    if abs(dts[0] - control_dt) > 1e-9:
        raise TTError(
            f"motions have dt = {dts[0]} s but IKConfig.control_dt = {control_dt} s; "
            "resample the motions or set control_dt to match"
        )
    for m, motion in enumerate(motions):
        if motion.arms != arms:
            raise TTError(
                f"motions[{m}] ({motion.name!r}) has {motion.arms} arm(s); the designs have {arms} end effector(s)"
            )


@runtime_checkable
class RolloutBackend(Protocol):
    """One batched simulator behind `tt.sim.rollout.rollout`.

    name: the backend's name (``rollout(backend=name)``); perturbs: whether it executes
    control perturbation (``action_noise`` > 0).
    """

    name: str
    perturbs: bool

    def resolve(self, designs: Sequence[Design | mujoco.MjModel]) -> Robots:
        """`resolve_designs` with the backend's constraints (raises for what it cannot run).
        The warp backend returns `tt.sim.designs.trees.DesignTrees` instead where the
        design space compiles its designs to tree fields itself (`DesignSpace.trees`)."""
        ...

    def run(
        self,
        robots: Robots,
        motions: Sequence[Motion],
        *,
        config: IKConfig,
        device: str,
        chunk: int | None,
        progress: bool,
        action_noise: float,
        noise_seed: int,
        threads: int | None = None,
        graph: bool | None = None,
    ) -> Episode:
        """Every robot on every motion: an Episode of W = D * M worlds, design-major (world
        ``d * M + m`` is design d on motion m), tensors on `device` (the oracle: CPU).
        chunk: control steps per kernel launch where the backend launches kernels.
        threads: CPU threads where the backend spreads worlds over threads (None: every
        core); the Episode must not depend on it. graph: replay the kernel launches as
        captured CUDA graphs (None: on a CUDA device; backends without kernel launches of
        their own ignore it)."""
        ...


__all__ = ["Robots", "RolloutBackend", "check_designs", "check_motions", "resolve_designs"]
