"""Normalisation of encoded tokens into [-1, 1] for diffusion, with statistics per attribute.

Each value of an attribute maps ``[low, high] -> [-1, 1]`` linearly, with ``low`` and
``high`` computed from a dataset (minimum and maximum, or quantiles) and stored with it.
Bits (binary attributes, the sign of a signed log) use [0, 1] and rotation entries
[-1, 1] whatever the data, so their meaning never depends on a dataset. Padding tokens get
`PAD_VALUE` in every value; `is_padding` finds them again in (noisy) model output.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np
import torch

from tt.tokens.batch import TokenBatch
from tt.tokens.schema import PAD_VALUE, SCHEMA, SCHEMA_VERSION, Encoding, check_version

#: Smallest range [low, high] a value gets; constant values map to 0.
MIN_RANGE = 1e-4
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


@dataclass
class Normalizer:
    """Per-value ranges of every token type: low[type], high[type] (width,) arrays."""

    low: dict[str, np.ndarray]
    high: dict[str, np.ndarray]
    version: int = SCHEMA_VERSION

    @staticmethod
    def fit(batches: Iterable[TokenBatch] | TokenBatch, quantile: float = 0.0) -> "Normalizer":
        """Statistics over the real tokens of a dataset (one batch or an iterable of them).

        quantile: 0 uses minimum and maximum (streaming); q > 0 uses the q and 1 - q
        quantiles (keeps every value in memory), so rare outliers do not squash the rest.
        """
        if isinstance(batches, TokenBatch):
            batches = [batches]
        if not 0.0 <= quantile < 0.5:
            raise ValueError(f"quantile must be in [0, 0.5), got {quantile}")
        lo: dict[str, np.ndarray] = {}
        hi: dict[str, np.ndarray] = {}
        kept: dict[str, list[np.ndarray]] = {}
        for b in batches:
            check_version(b.version, "a batch given to Normalizer.fit")
            for name in b.types:
                m = _np(b.mask[name]).astype(bool)
                v = _np(b.values[name]).astype(np.float64)[m]
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
            flo, fhi = _fixed_range(name)
            l = np.where(np.isnan(flo), lo[name], flo)
            h = np.where(np.isnan(fhi), hi[name], fhi)
            mid = 0.5 * (l + h)
            narrow = h - l < MIN_RANGE
            low[name] = np.where(narrow, mid - MIN_RANGE / 2, l)
            high[name] = np.where(narrow, mid + MIN_RANGE / 2, h)
        return Normalizer(low, high)

    def _range(self, name: str, like):
        if name not in self.low:
            raise KeyError(f"no statistics for token type {name!r}; the normalizer has {sorted(self.low)}")
        lo, hi = self.low[name], self.high[name]
        if isinstance(like, torch.Tensor):
            return torch.as_tensor(lo, dtype=like.dtype, device=like.device), torch.as_tensor(hi, dtype=like.dtype, device=like.device)
        return lo.astype(like.dtype), hi.astype(like.dtype)

    def normalize(self, batch: TokenBatch) -> TokenBatch:
        """Encoded tokens -> [-1, 1] (values outside the dataset's range go beyond);
        padding tokens -> `PAD_VALUE`."""
        check_version(batch.version, "normalized batch")
        values = {}
        for name in batch.types:
            v = batch.values[name]
            lo, hi = self._range(name, v)
            x = (v - lo) / (hi - lo) * 2 - 1
            m = batch.mask[name][..., None]
            values[name] = torch.where(m, x, torch.full_like(x, PAD_VALUE)) if isinstance(x, torch.Tensor) else np.where(m, x, PAD_VALUE).astype(v.dtype)
        return TokenBatch(values, dict(batch.ids), dict(batch.mask), batch.version)

    def unnormalize(self, batch: TokenBatch, detect_padding: bool = False, clip: bool = False) -> TokenBatch:
        """[-1, 1] -> encoded tokens. detect_padding: replace the mask with `is_padding` of
        the input (for model output); clip: clip to [-1, 1] first."""
        values, mask = {}, {}
        for name in batch.types:
            x = batch.values[name]
            if clip:
                x = x.clamp(-1, 1) if isinstance(x, torch.Tensor) else np.clip(x, -1, 1)
            lo, hi = self._range(name, x)
            values[name] = (x + 1) / 2 * (hi - lo) + lo
            mask[name] = ~is_padding(batch.values[name]) if detect_padding else batch.mask[name]
        return TokenBatch(values, dict(batch.ids), mask, batch.version)

    # ---------------------------------------------------------------- files
    def to_dict(self) -> dict:
        """JSON-ready: per type and attribute, the low and high of each value."""
        out = {"schema_version": self.version, "types": {}}
        for name in self.low:
            t = SCHEMA[name]
            out["types"][name] = {a.name: {"low": self.low[name][t.slice(a.name)].tolist(), "high": self.high[name][t.slice(a.name)].tolist()}
                                  for a in t.attributes}
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
                raise ValueError(f"statistics of {name!r} lack attributes {missing}")
            low[name] = np.concatenate([np.asarray(attrs[a.name]["low"], dtype=np.float64) for a in t.attributes])
            high[name] = np.concatenate([np.asarray(attrs[a.name]["high"], dtype=np.float64) for a in t.attributes])
        return Normalizer(low, high, int(data["schema_version"]))

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

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
