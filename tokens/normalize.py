"""Normalisation of token values into [-1, 1] for diffusion, with statistics per value.

Each value of a token type maps ``[low, high] -> [-1, 1]`` linearly, with ``low`` and
``high`` the minimum and maximum (or quantiles) of that value over the real tokens of a
dataset. For the schema's token types, bits (binary attributes, the sign of a signed log)
use [0, 1] and rotation entries [-1, 1] whatever the data, so their meaning never depends
on a dataset; other types (the DiT's generic test data) use the data's ranges throughout.
A fit widens ranges narrower than `MIN_RANGE` about their middle, so a value that is
constant over the data maps to 0. Padding tokens get `PAD_VALUE` in every value;
`is_padding` finds them again in (noisy) model output.

One `Normalizer` serves the tokenizer's numpy batches and the DiT's torch tensors (a
`tt.tokens.batch.TokenBatch` of either, or one type's values at a time, differentiably),
and is what datasets store (`to_dict`, JSON) and DiT checkpoints store (`state_dict`,
float32 tensors). It knows token types and widths, not model layouts:
`tt.dit.layout.Layout.check_normalizer` checks statistics against a layout.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from tt.kernels.errors import TTError
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import PAD_VALUE, SCHEMA, SCHEMA_VERSION, Encoding, check_version

#: Smallest range [low, high] a fit gives a value; constant values map to 0.
MIN_RANGE = 1e-4
#: Statistics with high - low below this (written by hand, or by DiT fits before the
#: normalisers were merged, which kept constant values at low == high) shift the value
#: (low -> 0) instead of scaling it.
CONSTANT_RANGE = 1e-6
#: A token is padding when the RMS distance of its normalised values to PAD_VALUE is below
#: this: far above model noise on padding (sigma 0.05 -> RMS 0.05), far below real tokens,
#: whose rotation entries alone keep them ~0.6 RMS away.
PADDING_RMS = 0.3


def _fixed_range(tname: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-value [low, high] fixed by the schema (NaN where the data decides)."""
    t = SCHEMA[tname]
    low = np.full(t.width, np.nan)
    high = np.full(t.width, np.nan)
    for a in t.attributes:
        sl = t.slice(a.name)
        if a.encoding is Encoding.BINARY:
            low[sl], high[sl] = 0.0, 1.0
        elif a.encoding is Encoding.ROTATION:
            low[sl], high[sl] = -1.0, 1.0
        elif a.encoding is Encoding.SIGNED_LOG:
            idx = np.arange(sl.start, sl.stop)
            low[idx[1::2]], high[idx[1::2]] = 0.0, 1.0
    return low, high


class Normalizer:
    """Per-type, per-value affine map ``x_n = 2 (x - low) / (high - low) - 1``.

    low, high: type -> (D,) float64 arrays, the range of each value over real tokens.
    version: RoboToken schema version of the data the statistics come from.
    """

    def __init__(self, low: Mapping, high: Mapping, version: int = SCHEMA_VERSION):
        if set(low) != set(high):
            raise TTError(f"low and high name different types: {sorted(low)} vs {sorted(high)}")
        self.low = {k: np.array(_np(v), dtype=np.float64) for k, v in low.items()}
        self.high = {k: np.array(_np(v), dtype=np.float64) for k, v in high.items()}
        self.version = int(version)
        for k in self.low:
            if self.low[k].ndim != 1 or self.low[k].shape != self.high[k].shape:
                raise TTError(
                    f"type {k!r}: low {self.low[k].shape} and high {self.high[k].shape} must be equal (D,) shapes"
                )
            if (self.high[k] < self.low[k]).any():
                raise TTError(f"type {k!r}: high < low in value {int(np.flatnonzero(self.high[k] < self.low[k])[0])}")

    def __repr__(self) -> str:
        widths = ", ".join(f"{k}: {len(v)}" for k, v in self.low.items())
        return f"Normalizer({{{widths}}}, version={self.version})"

    # ---------------------------------------------------------------- statistics
    @staticmethod
    def fit(data, quantile: float = 0.0) -> "Normalizer":
        """Statistics over the real tokens of a dataset.

        data: a `TokenBatch`; a mapping type -> (values (..., D), mask
        (...) True for real tokens); numpy or torch; or an iterable of these, streamed.
        quantile: 0 uses minimum and maximum (streaming); q > 0 uses the q and 1 - q
        quantiles (keeps every value in memory), so rare outliers do not squash the rest.
        A type without real tokens gets no statistics.
        """
        if not 0.0 <= quantile < 0.5:
            raise TTError(f"quantile must be in [0, 0.5), got {quantile}")
        parts = [data] if isinstance(data, (Mapping, TokenBatch)) else data
        lo: dict[str, np.ndarray] = {}
        hi: dict[str, np.ndarray] = {}
        kept: dict[str, list[np.ndarray]] = {}
        for part in parts:
            if isinstance(part, Mapping):
                items = [(name, v, m) for name, (v, m) in part.items()]
            else:
                check_version(part.version, "tokens given to Normalizer.fit")
                items = [(name, v, part.mask[name]) for name, v in part.values.items()]
            for name, values, mask in items:
                v = _np(values).astype(np.float64)[_np(mask).astype(bool)]  # (n, D)
                if name in SCHEMA.names() and v.shape[-1] != SCHEMA[name].width:
                    raise TTError(
                        f"values of token type {name!r} are {v.shape[-1]} wide; schema v{SCHEMA_VERSION} says "
                        f"{SCHEMA[name].width}"
                    )
                if not len(v):
                    continue
                if quantile > 0:
                    kept.setdefault(name, []).append(v)
                    continue
                lo[name] = np.minimum(lo[name], v.min(0)) if name in lo else v.min(0)
                hi[name] = np.maximum(hi[name], v.max(0)) if name in hi else v.max(0)
        for name, vs in kept.items():
            v = np.concatenate(vs)
            lo[name], hi[name] = np.quantile(v, quantile, axis=0), np.quantile(v, 1 - quantile, axis=0)
        low, high = {}, {}
        for name in lo:
            lower, h = lo[name], hi[name]
            if name in SCHEMA.names():
                flo, fhi = _fixed_range(name)
                lower, h = np.where(np.isnan(flo), lower, flo), np.where(np.isnan(fhi), h, fhi)
            mid = 0.5 * (lower + h)
            narrow = h - lower < MIN_RANGE
            low[name] = np.where(narrow, mid - MIN_RANGE / 2, lower)
            high[name] = np.where(narrow, mid + MIN_RANGE / 2, h)
        return Normalizer(low, high)

    # ---------------------------------------------------------------- the map
    def _affine(self, name: str, like):
        """(low, scale, offset) in the type, dtype and device of `like`, with
        ``x_n = (x - low) scale - offset``; subtracting low first keeps float32 precision
        on narrow ranges."""
        if name not in self.low:
            raise KeyError(f"no normalisation statistics for token type {name!r}; have {sorted(self.low)}")
        if isinstance(like, torch.Tensor):
            lo = torch.as_tensor(self.low[name], dtype=like.dtype, device=like.device)
            hi = torch.as_tensor(self.high[name], dtype=like.dtype, device=like.device)
            span = hi - lo
            const = span < CONSTANT_RANGE
            scale = torch.where(const, torch.ones_like(span), 2.0 / span.clamp_min(CONSTANT_RANGE))
            offset = torch.where(const, torch.zeros_like(span), torch.ones_like(span))
            return lo, scale, offset
        dtype = like.dtype if np.issubdtype(like.dtype, np.floating) else np.float64
        lo, hi = self.low[name].astype(dtype), self.high[name].astype(dtype)
        span = hi - lo
        const = span < CONSTANT_RANGE
        scale = np.where(const, 1.0, 2.0 / np.maximum(span, CONSTANT_RANGE)).astype(dtype)
        offset = np.where(const, 0.0, 1.0).astype(dtype)
        return lo, scale, offset

    def normalize_values(self, name: str, x, mask=None):
        """Values (..., D) of type `name` -> normalised (numpy or torch, differentiable);
        tokens where `mask` (...) is False become PAD_VALUE."""
        if not isinstance(x, torch.Tensor):
            x = np.asarray(x)
        lo, scale, offset = self._affine(name, x)
        y = (x - lo) * scale - offset
        if mask is None:
            return y
        if isinstance(y, torch.Tensor):
            return torch.where(mask.unsqueeze(-1), y, torch.full_like(y, PAD_VALUE))
        return np.where(np.asarray(mask)[..., None], y, PAD_VALUE).astype(y.dtype)

    def denormalize_values(self, name: str, y):
        """Normalised values (..., D) of type `name` -> encoded values (numpy or torch,
        differentiable)."""
        if not isinstance(y, torch.Tensor):
            y = np.asarray(y)
        lo, scale, offset = self._affine(name, y)
        return (y + offset) / scale + lo

    def normalize(self, tokens: TokenBatch) -> TokenBatch:
        """Every type of `tokens` (a `TokenBatch`) -> normalised, padding
        tokens -> PAD_VALUE (values beyond the dataset's range go beyond [-1, 1]). The
        result is of the same class; ids and mask are shared, not copied."""
        check_version(tokens.version, "normalized tokens")
        values = {k: self.normalize_values(k, v, tokens.mask[k]) for k, v in tokens.values.items()}
        return dataclasses.replace(tokens, values=values)

    def denormalize(self, tokens: TokenBatch, detect_padding: bool = False, clip: bool = False) -> TokenBatch:
        """Normalised `tokens` -> encoded values, of the same class.

        detect_padding: replace the mask with `is_padding` of the input (for model output);
        clip: clip to [-1, 1] first.
        """
        values, mask = {}, {}
        for name, y in tokens.values.items():
            x = (y.clamp(-1, 1) if isinstance(y, torch.Tensor) else np.clip(y, -1, 1)) if clip else y
            values[name] = self.denormalize_values(name, x)
            mask[name] = ~is_padding(y) if detect_padding else tokens.mask[name]
        return dataclasses.replace(tokens, values=values, mask=mask)

    # ---------------------------------------------------------------- files
    def state_dict(self) -> dict:
        """``{"low": {type: tensor}, "high": {type: tensor}}``, float32 on the CPU: what DiT
        checkpoints hold."""
        return {
            "low": {k: torch.tensor(v, dtype=torch.float32) for k, v in self.low.items()},
            "high": {k: torch.tensor(v, dtype=torch.float32) for k, v in self.high.items()},
        }

    @staticmethod
    def from_state_dict(state: Mapping) -> "Normalizer":
        """Inverse of `state_dict` (a checkpoint's ``"normalizer"`` entry)."""
        return Normalizer(state["low"], state["high"])

    def to_dict(self) -> dict:
        """JSON-ready: per type and attribute, the low and high of each value (schema types only)."""
        out = {"schema_version": self.version, "types": {}}
        for name in self.low:
            if name not in SCHEMA.names():
                raise TTError(
                    f"token type {name!r} is not in schema v{SCHEMA_VERSION} ({list(SCHEMA.names())}); "
                    "save its statistics with state_dict"
                )
            t = SCHEMA[name]
            out["types"][name] = {
                a.name: {
                    "low": self.low[name][t.slice(a.name)].tolist(),
                    "high": self.high[name][t.slice(a.name)].tolist(),
                }
                for a in t.attributes
            }
        return out

    @staticmethod
    def from_dict(data: dict) -> "Normalizer":
        """Inverse of `to_dict`; raises `SchemaVersionError` for another schema version."""
        check_version(data.get("schema_version", -1), "normalisation statistics")
        low, high = {}, {}
        for name, attrs in data["types"].items():
            t = SCHEMA[name]
            missing = [a.name for a in t.attributes if a.name not in attrs]
            if missing:
                raise TTError(f"statistics of {name!r} lack attributes {missing}")
            low[name] = np.concatenate([np.asarray(attrs[a.name]["low"], dtype=np.float64) for a in t.attributes])
            high[name] = np.concatenate([np.asarray(attrs[a.name]["high"], dtype=np.float64) for a in t.attributes])
        return Normalizer(low, high, int(data["schema_version"]))

    def save(self, path: str | Path) -> None:
        from tt.kernels.files import write_text

        write_text(path, json.dumps(self.to_dict(), indent=1))

    @staticmethod
    def load(path: str | Path) -> "Normalizer":
        return Normalizer.from_dict(json.loads(Path(path).read_text()))


def is_padding(values) -> np.ndarray | torch.Tensor:
    """(..., width) normalised tokens -> (...) True where a token is a padding token."""
    if isinstance(values, torch.Tensor):
        return ((values - PAD_VALUE) ** 2).mean(-1).sqrt() < PADDING_RMS
    return np.sqrt(((np.asarray(values) - PAD_VALUE) ** 2).mean(-1)) < PADDING_RMS


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)
