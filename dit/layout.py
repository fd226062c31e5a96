"""What the DiT sees: token specs (type, width, IDs, role, padded length) and layouts.

The model is generic over a `Layout`, a tuple of `TokenSpec`s, so it works for any schema;
`layout_from_schema` builds the layout of the RoboToken schema (`tt.tokens.schema`) for a
design space's largest robot. Sequences are concatenated in layout order, each type padded
to its `length`.

Each spec's `Role` (`tt.tokens.schema.Role`: embodiment, dynamics, action, condition)
decides what each diffusion task does with the type; see `Role` and `tt.dit.tasks`.

Tokens travel as `tt.tokens.batch.TokenBatch` of torch tensors: ``values[type]`` (B, L, D)
float, ``ids[type]`` (B, L, K) int64 in the order of ``spec.ids``, ``mask[type]`` (B, L)
bool, True for a real token and False for padding; `Layout.check` says whether a batch fits.
Per-step types are time-major: the ``per_step`` tokens of the window's first step, then
those of its second, and so on. Time IDs are control-step indices within the episode (as
`tt.tokens.episodes` writes them), so the time table must have more rows than the longest
episode has steps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import torch

from tt.kernels.errors import TTError
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import STEP_ROLES, Role


class LayoutError(TTError):
    """A token spec, layout or token tensor that does not fit together."""


@dataclass(frozen=True)
class TokenSpec:
    """One token type as the model sees it.

    name: type name; dim: width of one (encoded) token; ids: names of the ID kinds
    embedded for it, in the order of the last axis of ``ids[name]``; role: see `Role`;
    length: padded number of tokens of this type in one sequence; per_step: tokens per
    control step for step roles (``length = steps * per_step``), 0 for embodiment.
    """

    name: str
    dim: int
    ids: tuple[str, ...]
    role: Role
    length: int
    per_step: int = 0

    def __post_init__(self) -> None:
        if self.dim < 1:
            raise LayoutError(f"token type {self.name!r}: dim must be >= 1, got {self.dim}")
        if self.length < 1:
            raise LayoutError(f"token type {self.name!r}: length must be >= 1, got {self.length}")
        if not isinstance(self.role, Role):
            object.__setattr__(self, "role", Role(self.role))
        if self.role in STEP_ROLES:
            if "time" not in self.ids:
                raise LayoutError(
                    f"token type {self.name!r} has role {self.role.value} but no 'time' ID; ids: {self.ids}"
                )
            if self.per_step < 1 or self.length % self.per_step:
                raise LayoutError(
                    f"token type {self.name!r}: length {self.length} must be a positive multiple of per_step "
                    f"{self.per_step}"
                )
        elif self.per_step:
            raise LayoutError(f"token type {self.name!r}: embodiment types have per_step 0, got {self.per_step}")

    @property
    def time_index(self) -> int:
        """Position of the time ID on the last axis of ``ids[name]``."""
        return self.ids.index("time")

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "dim": self.dim,
            "ids": list(self.ids),
            "role": self.role.value,
            "length": self.length,
            "per_step": self.per_step,
        }

    @staticmethod
    def from_dict(d: Mapping) -> "TokenSpec":
        return TokenSpec(
            d["name"], int(d["dim"]), tuple(d["ids"]), Role(d["role"]), int(d["length"]), int(d["per_step"])
        )


@dataclass(frozen=True)
class Layout:
    """All token types of one model, in sequence order.

    specs: the token types; id_sizes: number of embedding rows per ID kind (IDs must lie in
    ``[0, id_sizes[kind])``); steps: control steps per window (8 in the paper);
    schema_version: RoboToken schema version of the types, None for layouts not built from
    the schema (tests).
    """

    specs: tuple[TokenSpec, ...]
    id_sizes: Mapping[str, int]
    steps: int = 8
    schema_version: int | None = None
    _by_name: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.specs:
            raise LayoutError("a layout needs at least one token type")
        for s in self.specs:
            if s.name in self._by_name:
                raise LayoutError(f"token type {s.name!r} appears twice in the layout")
            self._by_name[s.name] = s
            for k in s.ids:
                if k not in self.id_sizes or self.id_sizes[k] < 1:
                    raise LayoutError(
                        f"token type {s.name!r} uses ID kind {k!r}, which has no size; id_sizes: {dict(self.id_sizes)}"
                    )
            if s.per_step and s.length != self.steps * s.per_step:
                raise LayoutError(
                    f"token type {s.name!r}: length {s.length} != steps {self.steps} x per_step {s.per_step}"
                )
        if self.steps > self.id_sizes.get("time", self.steps):
            raise LayoutError(f"steps {self.steps} exceed the time ID size {self.id_sizes['time']}")

    def __getitem__(self, name: str) -> TokenSpec:
        if name not in self._by_name:
            raise KeyError(f"no token type {name!r} in the layout; types: {self.names}")
        return self._by_name[name]

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    @property
    def seq_len(self) -> int:
        """Length of the concatenated sequence."""
        return sum(s.length for s in self.specs)

    def names_with(self, *roles: Role) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs if s.role in roles)

    def to_dict(self) -> dict:
        return {
            "specs": [s.to_dict() for s in self.specs],
            "id_sizes": dict(self.id_sizes),
            "steps": self.steps,
            "schema_version": self.schema_version,
        }

    @staticmethod
    def from_dict(d: Mapping) -> "Layout":
        return Layout(
            tuple(TokenSpec.from_dict(s) for s in d["specs"]),
            {k: int(v) for k, v in d["id_sizes"].items()},
            int(d["steps"]),
            None if d["schema_version"] is None else int(d["schema_version"]),
        )

    def check(self, tokens: TokenBatch, *, check_ids: bool = True) -> None:
        """Raise `LayoutError` naming the first type of `tokens` (torch) whose shapes, dtypes or IDs
        do not fit this layout.

        The ID range check reads values back from the device; callers on a hot path
        check once per batch, not per diffusion step.
        """
        missing = [n for n in self.names if n not in tokens.values or n not in tokens.ids or n not in tokens.mask]
        if missing:
            raise LayoutError(f"tokens lack values, ids or mask of types {missing}; the layout has {list(self.names)}")
        b = len(tokens)
        for s in self.specs:
            v, i, m = tokens.values[s.name], tokens.ids[s.name], tokens.mask[s.name]
            if tuple(v.shape) != (b, s.length, s.dim):
                raise LayoutError(
                    f"values[{s.name!r}] has shape {tuple(v.shape)}, the layout needs {(b, s.length, s.dim)}"
                )
            if tuple(i.shape) != (b, s.length, len(s.ids)):
                raise LayoutError(
                    f"ids[{s.name!r}] has shape {tuple(i.shape)}, the layout needs "
                    f"{(b, s.length, len(s.ids))} (ids {s.ids})"
                )
            if tuple(m.shape) != (b, s.length) or m.dtype != torch.bool:
                raise LayoutError(
                    f"mask[{s.name!r}] has shape {tuple(m.shape)} and dtype {m.dtype}, the layout needs "
                    f"{(b, s.length)} bool"
                )
            if i.dtype != torch.int64:
                raise LayoutError(f"ids[{s.name!r}] has dtype {i.dtype}, expected torch.int64")
            if check_ids and i.numel():
                lo = i.amin(dim=(0, 1)).tolist()
                hi = i.amax(dim=(0, 1)).tolist()
                for k, kind in enumerate(s.ids):
                    if lo[k] < 0 or hi[k] >= self.id_sizes[kind]:
                        raise LayoutError(
                            f"ids[{s.name!r}] kind {kind!r} spans {lo[k]}..{hi[k]}; valid 0..{self.id_sizes[kind] - 1}"
                        )

    def check_normalizer(self, normalizer) -> None:
        """Raise `LayoutError` unless `normalizer` (a `tt.tokens.normalize.Normalizer`) has
        statistics of the right width for every type of this layout."""
        for s in self.specs:
            if s.name not in normalizer.low:
                raise LayoutError(f"normalisation statistics lack token type {s.name!r}")
            if normalizer.low[s.name].shape != (s.dim,):
                raise LayoutError(
                    f"normalisation statistics of {s.name!r} have width {normalizer.low[s.name].shape}, "
                    f"layout dim {s.dim}"
                )


def slot_ids(spec: TokenSpec, slots: int, id_sizes: Mapping[str, int]) -> torch.Tensor:
    """Positional IDs (slots, K) of `slots` consecutive tokens of `spec` (of one control step
    for step types), time IDs zero: slot i holds entity i, or entity i // 2 with order i % 2
    for types with a joint-order ID; clamped to the ID tables."""
    pos = torch.arange(slots)
    paired = "order" in spec.ids
    cols = []
    for kind in spec.ids:
        if kind == "time":
            cols.append(torch.zeros_like(pos))
        elif kind == "order":
            cols.append(pos % 2)
        else:
            cols.append((pos // 2 if paired else pos).clamp(max=id_sizes[kind] - 1))
    return torch.stack(cols, -1)


def with_slot_ids(layout: Layout, tokens: TokenBatch) -> TokenBatch:
    """`tokens` with every embodiment padding token carrying its slot's positional ID.

    The tokenizer writes ID 0 into padding slots, while real embodiment tokens carry their
    slot's ID. A motion-to-robot model trained on that learns which slots are padding from
    their IDs, but when it generates a robot (`tt.guidance.predicted.build_query`) every slot
    carries its positional ID, since the robot does not exist yet, and it then never emits
    padding (the step-6,500 ViperX checkpoint made every sample 7-DoF). Training on these
    IDs makes the IDs say nothing about padding, so the values must. Step types already
    carry positional IDs in their padding (`tt.tokens.episodes`).
    """
    ids = dict(tokens.ids)
    for s in layout.specs:
        if s.per_step:
            continue
        slot = slot_ids(s, s.length, layout.id_sizes).to(tokens.ids[s.name].device)
        ids[s.name] = torch.where(tokens.mask[s.name].unsqueeze(-1), tokens.ids[s.name], slot)
    return TokenBatch(tokens.values, ids, tokens.mask, tokens.version)


def robot_embodiment(layout: Layout, normalizer, models, device: str | torch.device = "cpu"):
    """Embodiment tokens of given robots as a model takes them: tokenized, padded to the
    layout's lengths, normalised (padding at PAD_VALUE, carrying its slot's positional ID,
    as `with_slot_ids` gives training batches).

    normalizer: the model's `tt.tokens.normalize.Normalizer`; models: compiled MuJoCo models.
    Returns (tokens, robots): a torch `TokenBatch` of the layout's embodiment types, (N, L, D)
    each, and the tokenizer's `RobotIndex` per robot. Raises LayoutError for a robot the
    layout cannot hold.
    """
    import warnings

    from tt.tokens.tokenize import Tokenizer, TokenizeWarning

    static = [s for s in layout.specs if s.role is Role.EMBODIMENT]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TokenizeWarning)
        emb = Tokenizer()(list(models))
    try:
        padded = emb.tokens.pad_to({s.name: s.length for s in static}).to_torch(str(device))
    except ValueError as e:
        raise LayoutError(f"a robot does not fit the model's layout: {e}") from None
    values = {
        s.name: normalizer.normalize_values(s.name, padded.values[s.name].float(), padded.mask[s.name]) for s in static
    }
    tokens = TokenBatch(
        values, {s.name: padded.ids[s.name] for s in static}, {s.name: padded.mask[s.name] for s in static}
    )
    return with_slot_ids(layout, tokens), emb.index


def layout_from_schema(counts: Mapping[str, int], *, steps: int = 8, max_time: int = 1024) -> Layout:
    """Layout of the RoboToken schema for a design space.

    counts: largest number of tokens of each type a robot of the space has, per robot for
    embodiment types and per control step for dynamics, control and target types (types
    with count 0 or absent are left out). steps: control steps per window; max_time:
    number of time-ID rows, more than the longest episode's steps (1024: 20 s at 50 Hz).

    Roles are the schema's; ID sizes come from the schema's bit widths.
    """
    from tt.tokens import schema as S

    unknown = [n for n in counts if n not in S.SCHEMA.names()]
    if unknown:
        raise LayoutError(
            f"counts name unknown token types {unknown}; schema v{S.SCHEMA_VERSION} has {list(S.SCHEMA.names())}"
        )
    roles = schema_roles()
    specs = []
    for t in S.SCHEMA.types:
        n = int(counts.get(t.name, 0))
        if n < 0:
            raise LayoutError(f"counts[{t.name!r}] = {n}; counts are >= 0")
        if n == 0:
            continue
        role = roles[t.name]
        if role is Role.EMBODIMENT:
            specs.append(TokenSpec(t.name, t.width, t.ids, role, n))
        else:
            specs.append(TokenSpec(t.name, t.width, t.ids, role, steps * n, n))
    id_sizes = {
        "link": S.MAX_LINKS,
        # Dynamic, ball and fixed joints share the "joint" kind; fixed joints can number
        # as many as links, which bounds all three.
        "joint": max(S.MAX_LINKS, S.MAX_DYNA_JOINTS),
        "order": 2,
        "actuator": S.MAX_DYNA_JOINTS,
        "free_link": max(S.MAX_FREE_LINKS, 1),
        "track_link": S.MAX_TRACK_LINKS,
        "time": max_time,
    }
    used = {k for s in specs for k in s.ids}
    return Layout(tuple(specs), {k: v for k, v in id_sizes.items() if k in used}, steps, S.SCHEMA_VERSION)


def schema_roles() -> dict[str, Role]:
    """Role of every RoboToken type (the schema's own: embodiment, dynamics, ``control`` ->
    action, ``target_pose`` -> condition)."""
    from tt.tokens import schema as S

    return {t.name: t.role for t in S.SCHEMA.types}
