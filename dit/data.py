"""Tokenized episodes in memory and the training windows cut from them.

`EpisodeTokens` holds E episodes: the embodiment tokens of each episode's robot (static,
per type (E, L, D)) and the per-step tokens of every control step (per type
(E, S, P, D): S steps, P tokens a step). A training window takes `steps` steps of one
episode (8 in the paper): random distinct steps, in time order, for motion-to-robot;
consecutive steps for control. Time IDs are the steps' indices in the episode, as
`tt.tokens.episodes` writes them; per-step tokens are laid out time-major.

`TokenSource` is what `tt.dit.train` needs from a dataset; `EpisodeTokens` is one, built
in memory or from `tt.tokens` batches (`EpisodeTokens.from_token_batches`).

Files (`save` / `load`) are ``.npz`` archives holding the arrays and a JSON header with
roles, ID names, ID sizes and the RoboToken schema version, checked on load.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Protocol

import numpy as np
import torch

from tt.dit.layout import Layout, LayoutError, TokenSpec
from tt.kernels.errors import TTError
from tt.kernels.files import CorruptFileError, atomic_write, read_npz, reason
from tt.tokens.batch import TokenBatch
from tt.tokens.normalize import Normalizer
from tt.tokens.schema import STEP_ROLES, Role

#: Format tag of `EpisodeTokens` files.
FILE_FORMAT = "tt.dit.episodes/1"


class TokenSource(Protocol):
    """Training data as `tt.dit.train` uses it."""

    def layout(self, steps: int = 8) -> Layout:
        """Token types and padded lengths for windows of `steps` control steps."""

    def fit_normalizer(self) -> Normalizer:
        """Normalisation statistics over the whole dataset."""

    def sample(
        self,
        n: int,
        steps: int,
        kind: str,
        generator: torch.Generator | None = None,
        part: tuple[int, int] | None = None,
    ) -> TokenBatch:
        """n raw (unnormalised) windows, drawn with `generator` (CPU); kind: "random" | "start" | "consecutive".
        part: (a, b): read only windows a .. b - 1 of the n drawn (a data-parallel rank's
        share); the generator advances as for all n."""


@dataclass
class EpisodeTokens:
    """E tokenized episodes (torch tensors on the CPU).

    roles: type -> Role; id_names: type -> ID kinds in the order of the ids' last axis
    (step types include "time"; its slot in `step_ids` is filled when windows are cut);
    id_sizes: embedding rows per ID kind; static_*: embodiment types, values (E, L, D)
    float32, ids (E, L, K) int64, mask (E, L) bool (True = real token); step_*: per-step
    types, values (E, S, P, D), ids (E, P, K), mask (E, P); lengths: (E,) valid steps of
    each episode (steps beyond are ignored); schema_version: RoboToken schema version, or
    None for data not made from the schema.
    """

    roles: dict[str, Role]
    id_names: dict[str, tuple[str, ...]]
    id_sizes: dict[str, int]
    static_values: dict[str, torch.Tensor]
    static_ids: dict[str, torch.Tensor]
    static_mask: dict[str, torch.Tensor]
    step_values: dict[str, torch.Tensor]
    step_ids: dict[str, torch.Tensor]
    step_mask: dict[str, torch.Tensor]
    lengths: torch.Tensor
    schema_version: int | None = None
    order: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        self.roles = {k: Role(v) for k, v in self.roles.items()}
        if not self.order:
            self.order = tuple(self.roles)
        if set(self.order) != set(self.roles):
            raise LayoutError(f"order {self.order} and roles {sorted(self.roles)} name different types")
        e = int(self.lengths.shape[0])
        s_max = None
        for name in self.order:
            role, ids = self.roles[name], tuple(self.id_names[name])
            if role in STEP_ROLES:
                v, i, m = self.step_values[name], self.step_ids[name], self.step_mask[name]
                if v.ndim != 4 or v.shape[0] != e:
                    raise LayoutError(f"step_values[{name!r}] has shape {tuple(v.shape)}, expected ({e}, S, P, D)")
                if s_max is None:
                    s_max = v.shape[1]
                if v.shape[1] != s_max:
                    raise LayoutError(f"step_values[{name!r}] has {v.shape[1]} steps, other types {s_max}")
                if "time" not in ids:
                    raise LayoutError(f"per-step type {name!r} has no 'time' ID; ids: {ids}")
                if tuple(i.shape) != (e, v.shape[2], len(ids)) or tuple(m.shape) != (e, v.shape[2]):
                    raise LayoutError(
                        f"step_ids/step_mask of {name!r} have shapes {tuple(i.shape)}/{tuple(m.shape)}, "
                        f"expected {(e, v.shape[2], len(ids))}/{(e, v.shape[2])}"
                    )
            else:
                v, i, m = self.static_values[name], self.static_ids[name], self.static_mask[name]
                if v.ndim != 3 or v.shape[0] != e:
                    raise LayoutError(f"static_values[{name!r}] has shape {tuple(v.shape)}, expected ({e}, L, D)")
                if tuple(i.shape) != (e, v.shape[1], len(ids)) or tuple(m.shape) != (e, v.shape[1]):
                    raise LayoutError(
                        f"static_ids/static_mask of {name!r} have shapes {tuple(i.shape)}/{tuple(m.shape)}, "
                        f"expected {(e, v.shape[1], len(ids))}/{(e, v.shape[1])}"
                    )
        if s_max is None:
            raise LayoutError("episodes need at least one per-step token type")
        if e == 0:
            raise LayoutError("no episodes")
        if int(self.lengths.min()) < 1 or int(self.lengths.max()) > s_max:
            raise LayoutError(
                f"episode lengths span {int(self.lengths.min())}..{int(self.lengths.max())}, valid 1..{s_max}"
            )

    def __len__(self) -> int:
        return int(self.lengths.shape[0])

    @property
    def max_steps(self) -> int:
        return int(next(iter(self.step_values.values())).shape[1])

    def layout(self, steps: int = 8) -> Layout:
        """The model layout for windows of `steps` steps (lengths from these arrays)."""
        specs = []
        for name in self.order:
            role, ids = self.roles[name], tuple(self.id_names[name])
            if role in STEP_ROLES:
                p, d = self.step_values[name].shape[2:]
                specs.append(TokenSpec(name, int(d), ids, role, steps * int(p), int(p)))
            else:
                count, d = self.static_values[name].shape[1:]
                specs.append(TokenSpec(name, int(d), ids, role, int(count)))
        layout = Layout(tuple(specs), dict(self.id_sizes), steps, self.schema_version)
        longest = int(self.lengths.max())
        if "time" in layout.id_sizes and longest > layout.id_sizes["time"]:
            raise LayoutError(f"episodes have up to {longest} steps but time IDs only {layout.id_sizes['time']} rows")
        return layout

    def fit_normalizer(self) -> Normalizer:
        """Per-feature ranges over real tokens (per-step types: over valid steps).

        Schema data uses `tt.tokens.normalize.Normalizer.fit`, so bits and rotation entries
        get the schema's fixed ranges and the statistics match what the detokenizer expects.
        """
        data = {}
        for name in self.order:
            if self.roles[name] in STEP_ROLES:
                v = self.step_values[name]
                valid = torch.arange(v.shape[1])[None, :] < self.lengths[:, None]  # (E, S)
                m = valid[:, :, None] & self.step_mask[name][:, None, :]  # (E, S, P)
                data[name] = (v.reshape(v.shape[0], -1, v.shape[-1]), m.reshape(m.shape[0], -1))
            else:
                data[name] = (self.static_values[name], self.static_mask[name])
        if self.schema_version is None:
            return Normalizer.fit(data)
        from tt.tokens.batch import TokenBatch

        ids = {k: np.zeros((*v.shape[:2], len(self.id_names[k])), np.int64) for k, (v, _) in data.items()}
        batch = TokenBatch(
            {k: v.numpy() for k, (v, _) in data.items()},
            ids,
            {k: m.numpy() for k, (_, m) in data.items()},
            self.schema_version,
        )
        return Normalizer.fit(batch)

    def window_steps(
        self, episodes: torch.Tensor, steps: int, kind: str, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Step indices (n, steps), ascending, of windows of the given episodes."""
        lengths = self.lengths[episodes]
        short = (lengths < steps).nonzero()
        if short.numel():
            i = int(episodes[short[0, 0]])
            raise LayoutError(f"episode {i} has {int(self.lengths[i])} steps, fewer than the window's {steps}")
        n = episodes.shape[0]
        if kind in ("random", "start"):
            scores = torch.rand(n, self.max_steps, generator=generator)
            scores = torch.where(
                torch.arange(self.max_steps)[None, :] < lengths[:, None], scores, torch.full_like(scores, 2.0)
            )
            if kind == "start":
                scores[:, 0] = -1.0  # step 0 always, then steps - 1 distinct others
            idx = scores.topk(steps, dim=1, largest=False).indices
            return idx.sort(dim=1).values
        if kind == "consecutive":
            start = (torch.rand(n, generator=generator) * (lengths - steps + 1)).long()
            return start[:, None] + torch.arange(steps)[None, :]
        raise TTError(f"window kind {kind!r} does not exist; kinds: random, start, consecutive")

    def window(self, episodes: torch.Tensor, step_index: torch.Tensor) -> TokenBatch:
        """Raw tokens of windows: episodes (n,) long, step_index (n, steps) from `window_steps`."""
        n, steps = step_index.shape
        time = step_index  # (n, steps): time IDs are episode step indices
        values, ids, mask = {}, {}, {}
        for name in self.order:
            if self.roles[name] in STEP_ROLES:
                v = self.step_values[name][episodes[:, None], step_index]  # (n, steps, P, D)
                p = v.shape[2]
                values[name] = v.reshape(n, steps * p, -1)
                i = self.step_ids[name][episodes][:, None].expand(n, steps, p, -1).clone()  # (n, steps, P, K)
                i[..., self.id_names[name].index("time")] = time[:, :, None]
                ids[name] = i.reshape(n, steps * p, -1)
                mask[name] = self.step_mask[name][episodes][:, None].expand(n, steps, p).reshape(n, steps * p)
            else:
                values[name] = self.static_values[name][episodes]
                ids[name] = self.static_ids[name][episodes]
                mask[name] = self.static_mask[name][episodes]
        return TokenBatch(values, ids, mask)

    def sample(
        self,
        n: int,
        steps: int,
        kind: str,
        generator: torch.Generator | None = None,
        part: tuple[int, int] | None = None,
    ) -> TokenBatch:
        """n windows of uniformly drawn episodes (raw, unnormalised tokens); part: (a, b) reads
        windows a .. b - 1 of them only (the draws are those of all n)."""
        episodes = torch.randint(0, len(self), (n,), generator=generator)
        step_index = self.window_steps(episodes, steps, kind, generator)
        rows = slice(*part) if part is not None else slice(None)
        return self.window(episodes[rows], step_index[rows])

    @staticmethod
    def from_token_batches(
        embodiment, dynamics, lengths: torch.Tensor, *, design_index: torch.Tensor | None = None, max_time: int = 1024
    ) -> "EpisodeTokens":
        """Episodes from `tt.tokens` output.

        embodiment: `TokenBatch` of the robots (`tokenize_models(...).tokens`), N robots;
        dynamics: `TokenBatch` of every step of E episodes (`episode_tokens` with
        ``step_index`` = all S steps of every world), per-step tokens time-major with the
        same number of tokens per step; lengths: (E,) executed steps; design_index: (E,)
        robot of each episode (default: episode e ran robot e); max_time: time-ID rows.
        """
        from tt.dit.layout import layout_from_schema, schema_roles

        roles = schema_roles()
        e = int(lengths.shape[0])
        design = torch.arange(e) if design_index is None else torch.as_tensor(design_index).long().cpu()
        emb = embodiment.to_torch("cpu")
        dyn = dynamics.to_torch("cpu")
        static_values, static_ids, static_mask = {}, {}, {}
        for name in emb.types:
            if roles[name] is not Role.EMBODIMENT:
                raise LayoutError(f"embodiment batch holds per-step type {name!r}")
            static_values[name], static_ids[name], static_mask[name] = (
                emb.values[name][design],
                emb.ids[name][design],
                emb.mask[name][design],
            )
        step_values, step_ids, step_mask = {}, {}, {}
        for name in dyn.types:
            if roles[name] is Role.EMBODIMENT:
                raise LayoutError(f"dynamics batch holds embodiment type {name!r}")
            v, i, m = dyn.values[name], dyn.ids[name], dyn.mask[name]
            if v.shape[0] != e:
                raise LayoutError(f"dynamics[{name!r}] has {v.shape[0]} episodes, lengths {e}")
            t = i[..., list(_schema_ids(name)).index("time")]  # (E, S*P)
            steps = int(t[0].max()) + 1 if t.numel() else 0
            if steps == 0 or v.shape[1] % steps:
                raise LayoutError(
                    f"dynamics[{name!r}] has {v.shape[1]} tokens, not a whole number per step over {steps} steps"
                )
            p = v.shape[1] // steps
            if not torch.equal(t.reshape(e, steps, p), torch.arange(steps)[None, :, None].expand(e, steps, p)):
                raise LayoutError(
                    f"dynamics[{name!r}] must hold every step 0..{steps - 1} of every episode, time-major "
                    "(episode_tokens with step_index = all steps)"
                )
            step_values[name] = v.reshape(e, steps, p, -1)
            step_ids[name] = i.reshape(e, steps, p, -1)[:, 0].clone()
            step_mask[name] = m.reshape(e, steps, p)[:, 0].clone()
        counts = {k: v.shape[1] for k, v in static_values.items()} | {k: v.shape[2] for k, v in step_values.items()}
        id_sizes = dict(layout_from_schema(counts, steps=1, max_time=max_time).id_sizes)
        order = tuple(n for n in roles if n in counts)
        return EpisodeTokens(
            {n: roles[n] for n in order},
            {n: _schema_ids(n) for n in order},
            id_sizes,
            static_values,
            static_ids,
            static_mask,
            step_values,
            step_ids,
            step_mask,
            lengths.long().cpu(),
            embodiment.version,
            order,
        )

    def subset(self, episodes: torch.Tensor) -> "EpisodeTokens":
        """The episodes at indices `episodes` (n,) long, in that order (copies)."""
        groups = {
            g: {n: x[episodes] for n, x in getattr(self, g).items()}
            for g in ("static_values", "static_ids", "static_mask", "step_values", "step_ids", "step_mask")
        }
        return EpisodeTokens(
            dict(self.roles),
            dict(self.id_names),
            dict(self.id_sizes),
            lengths=self.lengths[episodes],
            schema_version=self.schema_version,
            order=self.order,
            **groups,
        )

    def pad_to(self, counts: Mapping[str, int]) -> "EpisodeTokens":
        """Every type padded (never truncated) to ``counts[type]`` tokens per robot
        (embodiment types) or per step (per-step types); types not named keep their length."""

        def grow(x: torch.Tensor, axis: int, size: int, name: str) -> torch.Tensor:
            if x.shape[axis] > size:
                raise LayoutError(f"type {name!r} has {x.shape[axis]} tokens, more than the {size} asked for")
            shape = list(x.shape)
            shape[axis] = size - x.shape[axis]
            return torch.cat([x, torch.zeros(shape, dtype=x.dtype)], dim=axis)

        groups = {}
        for group, axis in (
            ("static_values", 1),
            ("static_ids", 1),
            ("static_mask", 1),
            ("step_values", 2),
            ("step_ids", 1),
            ("step_mask", 1),
        ):
            groups[group] = {
                n: grow(x, axis, counts[n], n) if n in counts else x for n, x in getattr(self, group).items()
            }
        return EpisodeTokens(
            dict(self.roles),
            dict(self.id_names),
            dict(self.id_sizes),
            lengths=self.lengths,
            schema_version=self.schema_version,
            order=self.order,
            **groups,
        )

    @staticmethod
    def concatenate(parts: list["EpisodeTokens"]) -> "EpisodeTokens":
        """Episodes of several sets (e.g. generation batches) in one, each type padded to
        the longest (tokens per robot, tokens per step, steps)."""
        if not parts:
            raise TTError("concatenate needs at least one EpisodeTokens")
        first = parts[0]
        for p in parts[1:]:
            if p.roles != first.roles or p.id_names != first.id_names or p.schema_version != first.schema_version:
                raise LayoutError("episode sets differ in token types, IDs or schema version")
        sizes = {k: max(p.id_sizes[k] for p in parts) for k in first.id_sizes}
        s_max = max(p.max_steps for p in parts)

        def pad(x: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
            out = torch.zeros((x.shape[0], *shape), dtype=x.dtype)
            out[(slice(None), *(slice(0, n) for n in x.shape[1:]))] = x
            return out

        groups = {}
        for group in ("static_values", "static_ids", "static_mask", "step_values", "step_ids", "step_mask"):
            merged = {}
            for name in getattr(first, group):
                xs = [getattr(p, group)[name] for p in parts]
                shape = tuple(max(x.shape[d] for x in xs) for d in range(1, xs[0].ndim))
                if group == "step_values":
                    shape = (s_max, *shape[1:])
                merged[name] = torch.cat([pad(x, shape) for x in xs])
            groups[group] = merged
        return EpisodeTokens(
            dict(first.roles),
            dict(first.id_names),
            sizes,
            lengths=torch.cat([p.lengths for p in parts]),
            schema_version=first.schema_version,
            order=first.order,
            **groups,
        )

    # ------------------------------------------------------------ files
    def save(self, path: str | Path) -> None:
        header = {
            "format": FILE_FORMAT,
            "order": list(self.order),
            "roles": {k: v.value for k, v in self.roles.items()},
            "id_names": {k: list(v) for k, v in self.id_names.items()},
            "id_sizes": self.id_sizes,
            "schema_version": self.schema_version,
        }
        arrays = {"header": np.array(json.dumps(header)), "lengths": self.lengths.numpy()}
        for group in ("static_values", "static_ids", "static_mask", "step_values", "step_ids", "step_mask"):
            for k, v in getattr(self, group).items():
                arrays[f"{group}/{k}"] = v.numpy()
        with atomic_write(path) as f:  # through a handle: np.savez appends .npz to names without it
            np.savez_compressed(f, **arrays)

    @staticmethod
    def load(path: str | Path) -> "EpisodeTokens":
        """Read a file written by `save`; raises FileNotFoundError, `CorruptFileError` naming the
        file and the entry that is missing, malformed or not finite, or SchemaVersionError."""
        path = Path(path)
        f = read_npz(path, "episode token file")
        what = f"episode token file {path}"
        if "header" not in f:
            raise CorruptFileError(f"{what} is not an episode token file (no 'header' entry)")
        try:
            header = json.loads(str(f["header"]))
        except (json.JSONDecodeError, RecursionError):
            raise CorruptFileError(f"{what}: its 'header' entry is not valid JSON") from None
        if not isinstance(header, dict) or header.get("format") != FILE_FORMAT:
            found = header.get("format") if isinstance(header, dict) else type(header).__name__
            raise CorruptFileError(f"{what} has format {found!r}, this code reads {FILE_FORMAT!r}")
        missing = [k for k in ("roles", "id_names", "id_sizes", "schema_version", "order") if k not in header]
        if missing or "lengths" not in f:
            raise CorruptFileError(f"{what} lacks {missing + ([] if 'lengths' in f else ['lengths'])}")
        if header["schema_version"] is not None:
            from tt.tokens.schema import check_version

            check_version(header["schema_version"], what)
        groups: dict[str, dict[str, torch.Tensor]] = {}
        for key, a in f.items():
            if "/" in key:
                group, name = key.split("/", 1)
                if a.dtype.kind not in "fiub":
                    raise CorruptFileError(f"{what}: entry {key!r} has dtype {a.dtype}, not numbers")
                if group.endswith("_values") and not np.isfinite(a).all():
                    raise CorruptFileError(f"{what}: entry {key!r} has NaN or infinite values")
                groups.setdefault(group, {})[name] = torch.from_numpy(a)
        try:
            return EpisodeTokens(
                roles={k: Role(v) for k, v in header["roles"].items()},
                id_names={k: tuple(v) for k, v in header["id_names"].items()},
                id_sizes={k: int(v) for k, v in header["id_sizes"].items()},
                static_values=groups.get("static_values", {}),
                static_ids=groups.get("static_ids", {}),
                static_mask=groups.get("static_mask", {}),
                step_values=groups.get("step_values", {}),
                step_ids=groups.get("step_ids", {}),
                step_mask=groups.get("step_mask", {}),
                lengths=torch.from_numpy(f["lengths"]),
                schema_version=header["schema_version"],
                order=tuple(header["order"]),
            )
        except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as e:
            raise CorruptFileError(f"{what} is malformed: {reason(e)}") from None


def _schema_ids(name: str) -> tuple[str, ...]:
    """ID kinds of a RoboToken type, from the schema."""
    from tt.tokens.schema import SCHEMA

    return tuple(SCHEMA[name].ids)
