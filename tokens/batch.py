"""`TokenBatch`: the one token container, from the tokenizer to the DiT and back.

RoboTokens of N robots (or N episode windows, or N model sequences) as padded fixed-width
arrays, per token type: numpy arrays on the host (tokenizer, dataset store, files) or
torch tensors on any device (the DiT, guidance, simulator gradients), never mixed.
`tt.dit.layout.Layout` says which types and lengths a model takes (`Layout.check`);
`tt.tokens.normalize.Normalizer` maps values to and from [-1, 1].
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.kernels.files import CorruptFileError, atomic_write, read_npz
from tt.tokens.schema import SCHEMA, SCHEMA_VERSION, check_version


@dataclass
class TokenBatch:
    """Tokens of N samples, per token type (numpy arrays or torch tensors, not mixed).

    values[type]: encoded (or normalised) tokens (N, L_type, D_type), float
    ids[type]: positional-embedding IDs (N, L_type, K_type), int64, in the order of the
        type's ID kinds (``SCHEMA[type].ids`` for schema types)
    mask[type]: True where a token is real, False for padding, (N, L_type) bool
    version: RoboToken schema version the tokens were written with

    Types absent from the dicts have no tokens in this batch. Schema types are checked
    against the schema's widths; other types (the DiT's generic test layouts) only for
    consistent shapes. Per-step types are time-major (the tokens of a window's first step,
    then its second, ...). The tokenizer's padding tokens hold zeros; normalised padding
    holds `tt.tokens.schema.PAD_VALUE`.
    """

    values: dict
    ids: dict
    mask: dict
    version: int = SCHEMA_VERSION

    def __post_init__(self) -> None:
        schema_names = SCHEMA.names()
        for name, v in self.values.items():
            if name not in self.ids or name not in self.mask:
                raise TTError(
                    f"token type {name!r} needs values, ids and mask; got ids={name in self.ids}, "
                    f"mask={name in self.mask}"
                )
            ids_shape, mask_shape = tuple(self.ids[name].shape), tuple(self.mask[name].shape)
            if name in schema_names:
                t = SCHEMA[name]
                if v.shape[-1] != t.width:
                    raise TTError(f"values[{name!r}] has width {v.shape[-1]}, schema v{SCHEMA_VERSION} says {t.width}")
                if ids_shape != (*v.shape[:2], len(t.ids)):
                    raise TTError(f"ids[{name!r}] has shape {ids_shape}, expected {(*v.shape[:2], len(t.ids))}")
            elif len(ids_shape) != 3 or ids_shape[:2] != tuple(v.shape[:2]):
                raise TTError(f"ids[{name!r}] has shape {ids_shape}, expected {(*v.shape[:2], 'K')}")
            if mask_shape != tuple(v.shape[:2]):
                raise TTError(f"mask[{name!r}] has shape {mask_shape}, expected {tuple(v.shape[:2])}")

    @property
    def types(self) -> tuple[str, ...]:
        """Token types present: schema types in schema order, then any others as given."""
        schema_names = SCHEMA.names()
        return tuple(n for n in schema_names if n in self.values) + tuple(
            n for n in self.values if n not in schema_names
        )

    def __len__(self) -> int:
        for v in self.values.values():
            return int(v.shape[0])
        return 0

    @property
    def device(self) -> torch.device:
        """Device of the (torch) values; ``cpu`` for numpy arrays."""
        for v in self.values.values():
            return v.device if isinstance(v, torch.Tensor) else torch.device("cpu")
        raise TTError("an empty TokenBatch has no device")

    def _map(self, fv, fi, fm) -> "TokenBatch":
        return TokenBatch(
            {n: fv(self.values[n]) for n in self.types},
            {n: fi(self.ids[n]) for n in self.types},
            {n: fm(self.mask[n]) for n in self.types},
            self.version,
        )

    def counts(self) -> dict[str, np.ndarray]:
        """Real tokens per type and sample: type -> (N,) int."""
        return {n: np.asarray(_np(self.mask[n]).sum(1)) for n in self.types}

    def total(self) -> np.ndarray:
        """Real tokens per sample over all types, (N,)."""
        out = np.zeros(len(self), dtype=np.int64)
        for c in self.counts().values():
            out += c
        return out

    def select(self, index) -> "TokenBatch":
        """Samples at `index`: an int (keeps the leading axis), a slice, an index array or
        tensor, or a boolean mask over N."""
        if isinstance(index, (int, np.integer)):
            index = slice(int(index), int(index) + 1)
        return self._map(lambda x: x[index], lambda x: x[index], lambda x: x[index])

    def subset(self, types: Sequence[str]) -> "TokenBatch":
        """Only the token types in `types` (those present)."""
        keep = [n for n in self.types if n in types]
        return TokenBatch(
            {n: self.values[n] for n in keep},
            {n: self.ids[n] for n in keep},
            {n: self.mask[n] for n in keep},
            self.version,
        )

    def merge(self, other: "TokenBatch") -> "TokenBatch":
        """Token types of both batches (same N); a type present in both is an error."""
        if len(self) != len(other) and self.values and other.values:
            raise TTError(f"cannot merge batches of {len(self)} and {len(other)} samples")
        both = set(self.types) & set(other.types)
        if both:
            raise TTError(f"both batches hold token types {sorted(both)}")
        check_version(other.version, "merged batch")
        return TokenBatch(
            {**self.values, **other.values}, {**self.ids, **other.ids}, {**self.mask, **other.mask}, self.version
        )

    def clone(self) -> "TokenBatch":
        """A copy that shares no memory with this batch."""

        def c(x):
            return x.clone() if isinstance(x, torch.Tensor) else np.array(x, copy=True)

        return self._map(c, c, c)

    def to(self, device: str | torch.device) -> "TokenBatch":
        """Torch tensors on `device`, dtypes kept (numpy arrays become tensors first)."""

        def t(x):
            return (x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))).to(device)

        return self._map(t, t, t)

    def to_torch(self, device: str = "cpu", dtype: torch.dtype = torch.float32) -> "TokenBatch":
        """Torch tensors on `device` (values in `dtype`, ids int64, mask bool)."""

        def t(x, dt):
            return (
                x.to(device=device, dtype=dt)
                if isinstance(x, torch.Tensor)
                else torch.as_tensor(np.asarray(x), device=device, dtype=dt)
            )

        return self._map(lambda x: t(x, dtype), lambda x: t(x, torch.int64), lambda x: t(x, torch.bool))

    def to_numpy(self, dtype=np.float32) -> "TokenBatch":
        """Numpy arrays on the host (values in `dtype`)."""
        return self._map(
            lambda x: _np(x).astype(dtype), lambda x: _np(x).astype(np.int64), lambda x: _np(x).astype(bool)
        )

    def pad_to(self, lengths: dict[str, int]) -> "TokenBatch":
        """Pad (never truncate) each type to ``lengths[type]`` tokens, as numpy arrays; absent
        schema types become empty arrays of that length when named in `lengths`. Raises
        naming a type that is too long."""
        values, ids, mask = {}, {}, {}
        n = len(self)
        for name in SCHEMA.names() + tuple(k for k in self.values if k not in SCHEMA.names()):
            if name not in lengths and name not in self.values:
                continue
            cur = self.values[name].shape[1] if name in self.values else 0
            want = lengths.get(name, cur)
            if cur > want:
                raise TTError(f"token type {name!r} has {cur} tokens, more than the requested length {want}")
            if name in self.values:
                v, i, m = _np(self.values[name]), _np(self.ids[name]), _np(self.mask[name])
            else:
                t = SCHEMA[name]
                v, i, m = (
                    np.zeros((n, 0, t.width), np.float32),
                    np.zeros((n, 0, len(t.ids)), np.int64),
                    np.zeros((n, 0), bool),
                )
            values[name] = np.concatenate([v, np.zeros((n, want - cur, v.shape[-1]), v.dtype)], 1)
            ids[name] = np.concatenate([i, np.zeros((n, want - cur, i.shape[-1]), i.dtype)], 1)
            mask[name] = np.concatenate([m, np.zeros((n, want - cur), bool)], 1)
        return TokenBatch(values, ids, mask, self.version)

    @staticmethod
    def concatenate(batches: Sequence["TokenBatch"]) -> "TokenBatch":
        """Stack batches along N. Torch batches (equal lengths per type, as a layout gives
        them) stay torch tensors on their device; numpy batches are padded to the longest
        of each type."""
        if not batches:
            raise TTError("concatenate needs at least one TokenBatch")
        for b in batches:
            check_version(b.version, "a concatenated batch")
        if all(isinstance(v, torch.Tensor) for b in batches for v in b.values.values()) and batches[0].values:
            names = batches[0].types
            for b in batches[1:]:
                if b.types != names:
                    raise TTError(f"cannot concatenate torch batches of types {list(names)} and {list(b.types)}")
            return TokenBatch(
                {n: torch.cat([b.values[n] for b in batches]) for n in names},
                {n: torch.cat([b.ids[n] for b in batches]) for n in names},
                {n: torch.cat([b.mask[n] for b in batches]) for n in names},
                batches[0].version,
            )
        names = [n for n in SCHEMA.names() if any(n in b.values for b in batches)]
        names += [n for b in batches for n in b.values if n not in SCHEMA.names() and n not in names]
        lengths = {n: max(b.values[n].shape[1] if n in b.values else 0 for b in batches) for n in names}
        padded = [b.pad_to(lengths) for b in batches]
        return TokenBatch(
            {n: np.concatenate([p.values[n] for p in padded]) for n in names},
            {n: np.concatenate([p.ids[n] for p in padded]) for n in names},
            {n: np.concatenate([p.mask[n] for p in padded]) for n in names},
        )

    # ---------------------------------------------------------------- files
    def save(self, path: str | Path) -> None:
        """Write an ``.npz`` with the arrays, the schema version and the schema description."""
        arrays = {"schema_version": np.array(self.version), "schema": np.array(json.dumps(SCHEMA.to_dict()))}
        for n in self.types:
            arrays[f"{n}/values"] = _np(self.values[n]).astype(np.float32)
            arrays[f"{n}/ids"] = _np(self.ids[n]).astype(np.int64)
            arrays[f"{n}/mask"] = _np(self.mask[n]).astype(bool)
        with atomic_write(path) as f:  # through a handle: np.savez appends .npz to names without it
            np.savez_compressed(f, **arrays)

    @staticmethod
    def load(path: str | Path) -> "TokenBatch":
        """Read a file written by `save`.

        Raises FileNotFoundError, `CorruptFileError` naming the file and the entry that is
        missing, malformed or not finite (a NaN in a real token would become a degenerate
        robot), or `SchemaVersionError` for another schema version.
        """
        path = Path(path)
        f = read_npz(path, "token file")
        if "schema_version" not in f:
            raise CorruptFileError(
                f"token file {path} is not a RoboToken file (no 'schema_version' entry; "
                "write one with `tt tokenize --out`)"
            )
        version = f["schema_version"]
        if version.shape != () or version.dtype.kind not in "iu":
            version = str(version) if version.dtype.kind in "US" else version.tolist()
        check_version(version, f"token file {path}")
        names = sorted({k.split("/")[0] for k in f if "/" in k})
        unknown = [n for n in names if n not in SCHEMA.names()]
        if unknown:
            raise CorruptFileError(
                f"token file {path} holds unknown token types {unknown}; schema v{SCHEMA_VERSION} "
                f"has {list(SCHEMA.names())}"
            )
        if not names:
            raise CorruptFileError(f"token file {path} holds no tokens")
        arrays: dict[str, dict] = {"values": {}, "ids": {}, "mask": {}}
        for n in names:
            for part, kinds in (("values", "f"), ("ids", "iu"), ("mask", "b")):
                key = f"{n}/{part}"
                if key not in f:
                    raise CorruptFileError(f"token file {path} lacks the entry {key!r}")
                if f[key].dtype.kind not in kinds:
                    raise CorruptFileError(
                        f"token file {path}: {key!r} has dtype {f[key].dtype}, expected {part} of kind {kinds!r}"
                    )
                arrays[part][n] = f[key]
            v, m = f[f"{n}/values"], f[f"{n}/mask"]
            if v.ndim != 3 or m.shape != v.shape[:2]:
                raise CorruptFileError(
                    f"token file {path}: {n!r} values {v.shape} and mask {m.shape} are not (N, L, D) and (N, L)"
                )
            bad = m & ~np.isfinite(v).all(-1)
            if bad.any():
                i, j = (int(x) for x in np.argwhere(bad)[0])
                raise CorruptFileError(f"token file {path}: {n!r} token {j} of robot {i} has NaN or infinite values")
        try:
            return TokenBatch(arrays["values"], arrays["ids"], arrays["mask"], int(version))
        except (ValueError, KeyError) as e:
            raise CorruptFileError(f"token file {path}: {e}") from None


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)
