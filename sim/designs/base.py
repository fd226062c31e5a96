"""Design spaces: procedural grammars whose designs are discrete + continuous choices.

A design is a list of discrete choices (indices into option tuples) and a list of
continuous choices; which parameters exist depends on earlier discrete choices (a 7-DoF
ViperX has more link lengths than a 5-DoF one). A design space turns a design into MJCF
text, and MJCF is the one source of truth for the robot afterwards.
"""

from __future__ import annotations

import json
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import mujoco
import numpy as np

from tt.kernels.errors import TTError
from tt.kernels.files import CorruptFileError, read_json

if TYPE_CHECKING:
    from tt.sim.designs.trees import DesignTrees


#: Fewest designs for which `DesignSpace.models` starts worker processes (a worker's start,
#: about a second of imports, must be won back by building its share of the models).
PARALLEL_MODELS_MIN = 512


def builds_in_workers(count: int, processes: int) -> bool:
    """Whether `DesignSpace.models` builds `count` designs in worker processes when given
    `processes` (more than one, and at least `PARALLEL_MODELS_MIN` designs)."""
    return processes > 1 and count >= PARALLEL_MODELS_MIN


def _build_models(space: str, designs: list) -> list[mujoco.MjModel]:
    """Worker of `DesignSpace.models`: the compiled models of `designs` of space `space`."""
    from tt.sim.designs import get_space

    sp = get_space(space)
    return [sp.model(d) for d in designs]


class DesignError(TTError):
    """A design that does not belong to its space; the message names the field."""


@dataclass(frozen=True)
class DiscreteParam:
    """One discrete choice: its name and the options it picks from."""

    name: str
    options: tuple[str, ...]


@dataclass(frozen=True)
class ContinuousParam:
    """One continuous choice with inclusive bounds, in SI units (m, rad)."""

    name: str
    low: float
    high: float
    unit: str = "m"

    @property
    def tolerance(self) -> float:
        """How far outside the bounds a value may lie and still count as inside: float
        round-off of values that came through float32."""
        return 1e-9 * max(1.0, abs(self.high - self.low))


@dataclass(frozen=True)
class Design:
    """One robot design of a space.

    discrete: option indices, one per `DesignSpace.discrete_params(discrete)` entry.
    continuous: values, one per `DesignSpace.continuous_params(discrete)` entry.
    """

    space: str
    discrete: tuple[int, ...]
    continuous: tuple[float, ...]


class DesignSpace(ABC):
    """A procedural robot grammar.

    Subclasses define the parameters, a nominal design and `to_mjcf`. Sampling, validation
    and the JSON form are shared.
    """

    name: str = ""
    #: True when the robot needs contact physics (a floor, feet); such designs cannot run
    #: on the contact-free `warp` rollout backend.
    has_contacts: bool = False
    #: Number of end effectors; their sites are named ``ee_0``, ``ee_1``, ...
    ee_count: int = 1
    #: Translation [m] that moves tt's library motions (authored for a table-top arm at the
    #: origin) into this robot's workspace; see `tt.sim.motions.for_space`.
    motion_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: Whether the library's placement at the base (`tt.sim.motions.place_at_base`, the
    #: paper's convention) holds for this robot. False for the quadruped: its motions stay
    #: where the skills were written, moved by `motion_offset` to the working height; the
    #: base placement is not yet tuned for a base that walks. The mobile bimanual robot,
    #: whose base rolls, keeps it and moves the placed motions in front of its base to its
    #: hands' height (`motion_offset`).
    places_motions: bool = True

    @property
    def family(self) -> str:
        """The full space this one belongs to (its own name; a `FixedStructureSpace`'s base):
        what reward weights and layouts are looked up by."""
        return self.name

    @abstractmethod
    def discrete_params(self, discrete: Sequence[int]) -> tuple[DiscreteParam, ...]:
        """The discrete parameters given (a prefix of) the discrete choices.

        Later parameters may depend on earlier choices; the result must be a function of
        the choices it depends on, and of those only.
        """

    @abstractmethod
    def continuous_params(self, discrete: Sequence[int]) -> tuple[ContinuousParam, ...]:
        """The continuous parameters for complete discrete choices."""

    @abstractmethod
    def nominal(self) -> Design:
        """The unmodified robot the grammar grows from."""

    @abstractmethod
    def _mjcf(self, discrete: tuple[int, ...], values: dict[str, float], options: dict[str, str]) -> str:
        """MJCF text for a validated design (options by name, values by name)."""

    # ---------------------------------------------------------------- shared machinery
    def ee_sites(self) -> tuple[str, ...]:
        """Site names of the end effectors, in the order motions address them."""
        return tuple(f"ee_{i}" for i in range(self.ee_count))

    def sample(self, n: int, seed: int) -> list[Design]:
        """`n` designs, discrete choices uniform over options, continuous uniform in bounds."""
        if n < 0:
            raise DesignError(f"n must be >= 0, got {n}")
        rng = np.random.default_rng(seed)
        designs = []
        for _ in range(n):
            discrete: list[int] = []
            while True:
                params = self.discrete_params(discrete)
                if len(discrete) == len(params):
                    break
                discrete.append(int(rng.integers(len(params[len(discrete)].options))))
            cparams = self.continuous_params(discrete)
            values = tuple(float(rng.uniform(p.low, p.high)) for p in cparams)
            designs.append(Design(self.name, tuple(discrete), values))
        return designs

    def validate(self, design: Design) -> None:
        """Raise `DesignError` naming the first field that is out of range or malformed."""
        if not isinstance(design, Design):
            raise DesignError(f"expected a Design, got {type(design).__name__}")
        if design.space != self.name:
            raise DesignError(f"design.space is {design.space!r}, this space is {self.name!r}")
        dparams = self.discrete_params(design.discrete)
        if len(design.discrete) != len(dparams):
            raise DesignError(
                f"design has {len(design.discrete)} discrete choices, space {self.name!r} expects "
                f"{len(dparams)}: {[p.name for p in dparams]}"
            )
        for i, (p, v) in enumerate(zip(dparams, design.discrete)):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or not 0 <= v < len(p.options):
                raise DesignError(
                    f"discrete[{i}] ({p.name!r}) = {v!r}; valid: an index in 0..{len(p.options) - 1} "
                    f"for options {list(p.options)}"
                )
            # A choice may change the parameters after it; re-read with this prefix.
            dparams_now = self.discrete_params(design.discrete[: i + 1])
            if dparams_now[: i + 1] != dparams[: i + 1]:
                raise DesignError(f"discrete choices are inconsistent at {p.name!r}")
        cparams = self.continuous_params(design.discrete)
        if len(design.continuous) != len(cparams):
            raise DesignError(
                f"design has {len(design.continuous)} continuous choices, space {self.name!r} expects "
                f"{len(cparams)} for these discrete choices: {[p.name for p in cparams]}"
            )
        for i, (p, v) in enumerate(zip(cparams, design.continuous)):
            if not isinstance(v, (float, int, np.floating)) or isinstance(v, bool) or not math.isfinite(v):
                raise DesignError(f"continuous[{i}] ({p.name!r}) = {v!r} is not a finite number")
            if not p.low - p.tolerance <= v <= p.high + p.tolerance:
                raise DesignError(
                    f"continuous[{i}] ({p.name!r}) = {v!r} {p.unit} is outside [{p.low}, {p.high}] {p.unit}"
                )

    def validate_many(self, designs: Sequence[Design]) -> None:
        """`validate` of every design (the first invalid one raises), with the discrete checks
        done once per distinct structure and the continuous bounds as arrays."""
        designs = list(designs)

        def in_order() -> None:  # where something is invalid: the first invalid design raises
            for design in designs:
                self.validate(design)

        by_structure: dict[tuple, list[Design]] = {}
        for design in designs:
            try:
                if not isinstance(design, Design):
                    raise TypeError
                # The types join the key: True == 1 would otherwise pass for a checked index.
                key = (design.space, tuple(design.discrete), tuple(type(v) for v in design.discrete))
                by_structure.setdefault(key, []).append(design)
            except TypeError:  # not a Design, or an unhashable choice
                return in_order()
        for members in by_structure.values():
            try:
                self.validate(members[0])
            except DesignError:
                return in_order()
            cparams = self.continuous_params(members[0].discrete)
            values = [design.continuous for design in members]
            ok = all(isinstance(row, (tuple, list, np.ndarray)) and len(row) == len(cparams) for row in values)
            if ok:
                types = {type(v) for row in values for v in row}
                ok = all(issubclass(t, (float, int, np.floating)) and not issubclass(t, bool) for t in types)
            if ok:
                tol = np.array([p.tolerance for p in cparams])
                low, high = np.array([p.low for p in cparams]) - tol, np.array([p.high for p in cparams]) + tol
                try:
                    x = np.array(values, dtype=float).reshape(len(members), len(cparams))
                except (OverflowError, ValueError, TypeError):  # e.g. an int beyond float range
                    return in_order()
                ok = bool(np.all(np.isfinite(x)) and np.all(low <= x) and np.all(x <= high))
            if not ok:
                return in_order()

    def to_mjcf(self, design: Design) -> str:
        """MJCF text of a design that `mujoco.MjModel.from_xml_string` loads."""
        self.validate(design)
        dparams = self.discrete_params(design.discrete)
        options = {p.name: p.options[i] for p, i in zip(dparams, design.discrete)}
        cparams = self.continuous_params(design.discrete)
        values = {p.name: float(v) for p, v in zip(cparams, design.continuous)}
        return self._mjcf(tuple(int(i) for i in design.discrete), values, options)

    def model(self, design: Design) -> mujoco.MjModel:
        """The compiled MuJoCo model of a design."""
        return mujoco.MjModel.from_xml_string(self.to_mjcf(design))

    def trees(self, designs: Sequence[Design]) -> "DesignTrees | None":
        """The designs compiled straight to tree-model fields (`tt.sim.designs.trees.DesignTrees`),
        without MJCF or MuJoCo's compiler, for the warp backend; None where the space has no
        such builder (its designs go through `models`). A space with a builder raises
        `DesignError` for an invalid design."""
        return None

    def models(self, designs: Sequence[Design], *, processes: int = 1) -> list[mujoco.MjModel]:
        """The compiled models of `designs`, in order (`model` of each).

        processes > 1 and at least `PARALLEL_MODELS_MIN` designs: the designs are built in
        that many spawned worker processes, a contiguous chunk each, and their models
        unpickled here (MJCF generation is Python and MuJoCo's compiler holds the GIL, so
        threads would not help; unpickling a model costs a fraction of compiling it). The
        models are the same either way: pickling is MuJoCo's binary model format.
        """
        designs = list(designs)
        if not builds_in_workers(len(designs), processes):
            return [self.model(d) for d in designs]
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        processes = min(processes, len(designs))
        cuts = [len(designs) * k // processes for k in range(processes + 1)]
        # spawn: a forked child would inherit this process's Warp/torch/OpenMP thread state.
        with ProcessPoolExecutor(processes, mp_context=mp.get_context("spawn")) as pool:
            parts = pool.map(
                _build_models, [self.name] * processes, [designs[lo:hi] for lo, hi in zip(cuts[:-1], cuts[1:])]
            )
            return [m for part in parts for m in part]

    # ---------------------------------------------------------------- JSON
    def to_dict(self, design: Design) -> dict:
        """JSON-ready form: choices by name, so files stay readable and diffable."""
        self.validate(design)
        dparams = self.discrete_params(design.discrete)
        cparams = self.continuous_params(design.discrete)
        return {
            "space": self.name,
            "discrete": {p.name: p.options[i] for p, i in zip(dparams, design.discrete)},
            "continuous": {p.name: float(v) for p, v in zip(cparams, design.continuous)},
        }

    def from_dict(self, data: dict) -> Design:
        """Inverse of `to_dict`; raises `DesignError` naming a missing or unknown field."""
        if not isinstance(data, dict):
            raise DesignError(f"a design must be a JSON object, got {type(data).__name__}")
        if data.get("space") != self.name:
            raise DesignError(f"field 'space' is {data.get('space')!r}, expected {self.name!r}")
        dnamed = data.get("discrete")
        cnamed = data.get("continuous")
        if not isinstance(dnamed, dict) or not isinstance(cnamed, dict):
            raise DesignError("fields 'discrete' and 'continuous' must be JSON objects")
        discrete: list[int] = []
        while True:
            params = self.discrete_params(discrete)
            if len(discrete) == len(params):
                break
            p = params[len(discrete)]
            if p.name not in dnamed:
                raise DesignError(f"discrete field {p.name!r} is missing; options: {list(p.options)}")
            option = str(dnamed[p.name])
            if option not in p.options:
                raise DesignError(f"discrete field {p.name!r} = {option!r}; valid options: {list(p.options)}")
            discrete.append(p.options.index(option))
        extra = set(dnamed) - {p.name for p in params}
        if extra:
            raise DesignError(f"unknown discrete fields {sorted(extra)} for space {self.name!r}")
        cparams = self.continuous_params(discrete)
        extra = set(cnamed) - {p.name for p in cparams}
        if extra:
            raise DesignError(f"unknown continuous fields {sorted(extra)} for these discrete choices")
        values = []
        for p in cparams:
            if p.name not in cnamed:
                raise DesignError(f"continuous field {p.name!r} is missing ([{p.low}, {p.high}] {p.unit})")
            v = cnamed[p.name]
            if not isinstance(v, (int, float)) or isinstance(v, bool):
                raise DesignError(f"continuous field {p.name!r} = {v!r} is not a number")
            if isinstance(v, int) and abs(v) > 1e300:  # float() of a huge JSON integer overflows
                raise DesignError(
                    f"continuous field {p.name!r} is an integer beyond 1e300, outside [{p.low}, {p.high}] {p.unit}"
                )
            values.append(float(v))
        design = Design(self.name, tuple(discrete), tuple(values))
        self.validate(design)
        return design


def save_designs(designs: Sequence[Design], path: str | Path, *, files: Sequence[str] | None = None) -> None:
    """Write designs to a JSON file: ``{"designs": [...]}`` (`tt.kernels.files.atomic_write`:
    the old file stays whole until the new one is; ``-`` is stdout). files: also record
    these file names (``"files"``: the MJCF files ``tt designs`` wrote beside it, the only
    ones a later run there removes)."""
    from tt.kernels.files import write_text
    from tt.sim.designs import get_space

    data: dict = {"designs": [get_space(d.space).to_dict(d) for d in designs]}
    if files is not None:
        data["files"] = list(files)
    write_text(path, json.dumps(data, indent=1))


def design_items(data, path: str | Path) -> list:
    """The design objects (not yet checked) in the parsed JSON of a file tt wrote, in order.

    Every form tt writes designs in: ``{"designs": [...]}`` (``tt designs``, ``tt rollout
    --out``, ``tt validate --json``, ``tt detokenize --space``), ``{"design": {...}, ...}``
    (``tt optimize --json``), ``{"designs": {label: {...}, ...}}`` (``tt demo``'s
    demo.json, in its order), and a bare design or list of designs.
    """
    # tt optimize --json's file has its 'space' beside 'design': a design's own fields decide
    if (
        isinstance(data, dict)
        and not {"discrete", "continuous"} & set(data)
        and ("designs" in data or "design" in data)
    ):
        if "designs" in data:
            items = data["designs"]
            if (
                isinstance(items, dict)
                and "space" not in items
                and items
                and all(isinstance(v, dict) for v in items.values())
            ):
                items = list(items.values())  # labelled designs
        else:
            items = [data["design"]]
    elif isinstance(data, dict) and not {"space", "discrete", "continuous"} & set(data):
        raise DesignError(
            f"{path} holds no designs: expected a design file tt wrote ('designs': [...] from "
            f"`tt designs`, or 'design': {{...}} from `tt optimize --json`); its fields are {sorted(data)[:8]}"
        )
    else:
        items = data
    if isinstance(items, dict):
        items = [items]
    if not isinstance(items, list):
        raise DesignError(f"{path}: expected a list of designs or {{'designs': [...]}}")
    return items


def load_designs(spec: str | Path) -> list[Design]:
    """Read designs from a design file tt wrote (`design_items` lists the forms), all of them
    or one with ``FILE#i``."""
    from tt.sim.designs import get_space

    spec = str(spec)
    index = None
    if "#" in spec:
        spec, idx = spec.rsplit("#", 1)
        try:
            index = int(idx)
        except ValueError:
            raise DesignError(f"design index {idx!r} after '#' is not an integer") from None
    path = Path(spec)
    try:
        data = read_json(path, "design file")
    except CorruptFileError as e:
        raise DesignError(str(e)) from None
    items = design_items(data, path)
    if not items:
        raise DesignError(f"{path} holds no designs")
    numbers = list(range(len(items)))
    if index is not None:
        if not -len(items) <= index < len(items):
            raise DesignError(f"design index {index} out of range: {path} holds {len(items)} designs")
        numbers = [numbers[index]]
    designs = []
    for k in numbers:
        item = items[k]
        where = f"{path}: design #{k} of {len(items)}"
        if not isinstance(item, dict) or "space" not in item:
            raise DesignError(f"{where} has no 'space' field")
        if not isinstance(item["space"], str):
            raise DesignError(f"{where}: field 'space' is {item['space']!r}, not a name")
        try:
            designs.append(get_space(item["space"]).from_dict(item))
        except DesignError as e:
            raise DesignError(f"{where}: {e}") from None
    return designs


class FixedStructureSpace(DesignSpace):
    """A sub-space of `base` with its discrete choices fixed and its continuous choices free.

    A rung of the learnability ladder (one kinematic structure, so a model only has to
    learn how lengths and mount poses change the motion), and a space of its own for every
    command: designs, MJCF, tokens and rewards are `base`'s. Its discrete parameters keep
    `base`'s names with one option each (the fixed one), so its designs' JSON reads like
    `base`'s and their discrete indices are all 0.

    name: the sub-space's name; base: the full space; discrete: `base`'s complete discrete
    choices to fix (option indices).
    """

    def __init__(self, name: str, base: DesignSpace, discrete: Sequence[int]):
        fixed = tuple(int(i) for i in discrete)
        params = base.discrete_params(fixed)
        if len(fixed) != len(params):
            raise DesignError(
                f"sub-space {name!r}: {len(fixed)} discrete choices given, space {base.name!r} "
                f"needs {len(params)}: {[p.name for p in params]}"
            )
        for i, (p, v) in enumerate(zip(params, fixed)):
            if not 0 <= v < len(p.options):
                raise DesignError(
                    f"sub-space {name!r}: discrete[{i}] ({p.name!r}) = {v}; valid: 0..{len(p.options) - 1}"
                )
        self.name = name
        self.base = base
        self.fixed = fixed
        self.has_contacts = base.has_contacts
        self.ee_count = base.ee_count
        self.motion_offset = base.motion_offset
        self.places_motions = base.places_motions
        self._params = tuple(DiscreteParam(p.name, (p.options[i],)) for p, i in zip(params, fixed))

    @property
    def family(self) -> str:
        return self.base.family

    def discrete_params(self, discrete: Sequence[int]) -> tuple[DiscreteParam, ...]:
        return self._params

    def continuous_params(self, discrete: Sequence[int]) -> tuple[ContinuousParam, ...]:
        return self.base.continuous_params(self.fixed)

    def nominal(self) -> Design:
        base = self.base.nominal()
        if base.discrete == self.fixed:
            values = base.continuous
        else:
            values = tuple(0.5 * (p.low + p.high) for p in self.continuous_params(()))
        return Design(self.name, (0,) * len(self.fixed), values)

    def _mjcf(self, discrete, values, options) -> str:
        return self.base._mjcf(self.fixed, values, options)

    def trees(self, designs: Sequence[Design]) -> "DesignTrees | None":
        """`base`'s tree fields of the same robots (see `DesignSpace.trees`)."""
        from dataclasses import replace

        self.validate_many(designs)
        out = self.base.trees([Design(self.base.name, self.fixed, tuple(d.continuous)) for d in designs])
        return None if out is None else replace(out, space=self.name)

    def to_base(self, design: Design) -> Design:
        """The same robot as a design of `base`."""
        self.validate(design)
        return Design(self.base.name, self.fixed, tuple(design.continuous))

    def from_base(self, design: Design) -> Design:
        """A design of `base` with this sub-space's discrete choices as a design of the sub-space."""
        self.base.validate(design)
        if tuple(design.discrete) != self.fixed:
            raise DesignError(
                f"design's discrete choices {list(design.discrete)} are not sub-space {self.name!r}'s "
                f"{list(self.fixed)}"
            )
        return Design(self.name, (0,) * len(self.fixed), tuple(design.continuous))
