"""Per-feature min-max normalisation of token values to [-1, 1], with padding at PAD_VALUE.

Diffusion works in normalised space: every feature of every real token lies in [-1, 1]
over the training data (binary codes {0, 1} become {-1, 1}), so the sampler's x0 clip at
+-1 is the data range, and every padding token is PAD_VALUE (-1) in every feature, the
"special value" the detokenizer detects. A feature that is constant over the data maps to
0 (it is shifted, not scaled).
"""

from __future__ import annotations

from typing import Mapping

import torch

from tt.dit.layout import PAD_VALUE, Layout, LayoutError, TokenTensors

#: Ranges narrower than this are treated as constant features.
_MIN_RANGE = 1e-6


class Normalizer:
    """Per-type, per-feature affine map ``x_n = 2 (x - low) / (high - low) - 1``.

    low, high: type -> (D,) float32 tensors, the range of each feature over real tokens.
    """

    def __init__(self, low: Mapping[str, torch.Tensor], high: Mapping[str, torch.Tensor]):
        if set(low) != set(high):
            raise ValueError(f"low and high name different types: {sorted(low)} vs {sorted(high)}")
        self.low = {k: v.detach().float().cpu() for k, v in low.items()}
        self.high = {k: v.detach().float().cpu() for k, v in high.items()}
        for k in self.low:
            if self.low[k].shape != self.high[k].shape:
                raise ValueError(f"type {k!r}: low {tuple(self.low[k].shape)} and high {tuple(self.high[k].shape)} differ in shape")
            if bool((self.high[k] < self.low[k]).any()):
                raise ValueError(f"type {k!r}: high < low in feature {int((self.high[k] < self.low[k]).nonzero()[0])}")

    @staticmethod
    def fit(tokens: Mapping[str, tuple[torch.Tensor, torch.Tensor]]) -> "Normalizer":
        """Ranges from data. tokens: type -> (values (..., D), mask (...) bool of real tokens).

        A type without any real token gets low = high = 0.
        """
        low, high = {}, {}
        for name, (values, mask) in tokens.items():
            real = values[mask]  # (n, D)
            if real.shape[0] == 0:
                low[name] = torch.zeros(values.shape[-1])
                high[name] = torch.zeros(values.shape[-1])
            else:
                low[name] = real.amin(0).float()
                high[name] = real.amax(0).float()
        return Normalizer(low, high)

    def _affine(self, name: str, device, dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(low, scale, offset) with x_n = (x - low) scale - offset; subtracting low first keeps
        float32 precision on narrow ranges."""
        if name not in self.low:
            raise KeyError(f"no normalisation statistics for token type {name!r}; have {sorted(self.low)}")
        lo, hi = self.low[name].to(device, dtype), self.high[name].to(device, dtype)
        span = hi - lo
        const = span < _MIN_RANGE
        scale = torch.where(const, torch.ones_like(span), 2.0 / span.clamp_min(_MIN_RANGE))
        offset = torch.where(const, torch.zeros_like(span), torch.ones_like(span))
        return lo, scale, offset

    def normalize_values(self, name: str, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Raw values (..., D) -> normalised; tokens where ``mask`` is False become PAD_VALUE."""
        lo, scale, offset = self._affine(name, x.device, x.dtype)
        y = (x - lo) * scale - offset
        if mask is not None:
            y = torch.where(mask.unsqueeze(-1), y, torch.full_like(y, PAD_VALUE))
        return y

    def denormalize_values(self, name: str, y: torch.Tensor) -> torch.Tensor:
        """Normalised values (..., D) -> raw values (differentiable)."""
        lo, scale, offset = self._affine(name, y.device, y.dtype)
        return (y + offset) / scale + lo

    def normalize(self, tokens: TokenTensors) -> TokenTensors:
        """All types of `tokens`, padding set to PAD_VALUE; ids and mask are shared, not copied."""
        return TokenTensors({k: self.normalize_values(k, v, tokens.mask[k]) for k, v in tokens.values.items()}, tokens.ids, tokens.mask)

    def denormalize(self, tokens: TokenTensors) -> TokenTensors:
        return TokenTensors({k: self.denormalize_values(k, v) for k, v in tokens.values.items()}, tokens.ids, tokens.mask)

    def check(self, layout: Layout) -> None:
        """Raise `LayoutError` unless every layout type has statistics of its width."""
        for s in layout.specs:
            if s.name not in self.low:
                raise LayoutError(f"normalisation statistics lack token type {s.name!r}")
            if self.low[s.name].shape != (s.dim,):
                raise LayoutError(f"normalisation statistics of {s.name!r} have width {tuple(self.low[s.name].shape)}, layout dim {s.dim}")

    @staticmethod
    def from_schema_normalizer(stats) -> "Normalizer":
        """From `tt.tokens.normalize.Normalizer` statistics (same affine map)."""
        return Normalizer({k: torch.as_tensor(v) for k, v in stats.low.items()}, {k: torch.as_tensor(v) for k, v in stats.high.items()})

    def to_schema_normalizer(self):
        """As `tt.tokens.normalize.Normalizer`, e.g. for its ``unnormalize(..., detect_padding=True)``."""
        from tt.tokens.normalize import Normalizer as SchemaNormalizer

        return SchemaNormalizer({k: v.double().numpy() for k, v in self.low.items()}, {k: v.double().numpy() for k, v in self.high.items()})

    def state_dict(self) -> dict:
        return {"low": {k: v.clone() for k, v in self.low.items()}, "high": {k: v.clone() for k, v in self.high.items()}}

    @staticmethod
    def from_state_dict(state: Mapping) -> "Normalizer":
        return Normalizer(state["low"], state["high"])
