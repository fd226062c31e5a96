"""Diffusion composition for multi-trajectory optimization (Liu et al. 2022; Du et al. 2023).

One design must serve M motions. The composed process diffuses one sequence per candidate
that holds the embodiment tokens once and the per-step tokens (dynamics, actions, target
conditioning) of every motion, renamed ``<type>@<m>``. `ComposedModel` wraps the network
so that `tt.dit.sample` runs this sequence like any other: each step it splits the
candidate into M ordinary sequences (copy m: the shared embodiment tokens and motion m's
per-step tokens), runs the network on all n x M copies in one batch, and returns

* for embodiment tokens, the mean over the M copies of their predicted eps (the product of
  the M conditionals' experts, each weighed equally);
* for motion m's per-step tokens, copy m's own eps.

The copies stay consistent by construction: the embodiment exists once in the sampler's
state, so the initial noise, every DDIM step and every eta > 0 draw act on one set of
embodiment tokens. With M = 1 the composed layout equals the model's (names aside, same
order and shapes) and the sampler draws the same noise, so composing one motion gives the
same samples as not composing.
"""

from __future__ import annotations

from typing import Iterable, Mapping, Sequence

import torch
import torch.nn as nn

from tt.dit.layout import Layout, LayoutError, TokenSpec
from tt.kernels.errors import TTError
from tt.tokens.batch import TokenBatch
from tt.tokens.schema import STEP_ROLES

#: Separator between a type name and its motion index in composed layouts.
SEPARATOR = "@"


def copy_name(name: str, motion: int) -> str:
    return f"{name}{SEPARATOR}{motion}"


def composed_layout(layout: Layout, motions: int) -> Layout:
    """The layout of a candidate composed over `motions` motions: embodiment types once,
    every per-step type once per motion (``<type>@<m>``), in the model's type order with a
    type's copies side by side."""
    if motions < 1:
        raise TTError(f"motions must be >= 1, got {motions}")
    bad = [s.name for s in layout.specs if SEPARATOR in s.name]
    if bad:
        raise LayoutError(f"token types {bad} contain {SEPARATOR!r}, which composed layouts reserve")
    specs = []
    for s in layout.specs:
        if s.role in STEP_ROLES:
            specs += [
                TokenSpec(copy_name(s.name, m), s.dim, s.ids, s.role, s.length, s.per_step) for m in range(motions)
            ]
        else:
            specs.append(s)
    return Layout(tuple(specs), dict(layout.id_sizes), layout.steps, layout.schema_version)


def compose_tokens(layout: Layout, parts: Sequence[TokenBatch]) -> TokenBatch:
    """One composed sequence per candidate from M per-motion token sets of n sequences each
    (embodiment values, IDs and masks from the first)."""
    first = parts[0]
    values, ids, mask = {}, {}, {}
    for s in layout.specs:
        if s.role in STEP_ROLES:
            for m, p in enumerate(parts):
                c = copy_name(s.name, m)
                values[c], ids[c], mask[c] = p.values[s.name], p.ids[s.name], p.mask[s.name]
        else:
            values[s.name], ids[s.name], mask[s.name] = first.values[s.name], first.ids[s.name], first.mask[s.name]
    return TokenBatch(values, ids, mask)


def split_values(layout: Layout, composed: Mapping[str, torch.Tensor], motions: int) -> list[dict[str, torch.Tensor]]:
    """Per-motion dicts type -> tensor of the model's layout from a composed dict (types
    absent from `composed` are left out); embodiment entries are shared, not copied."""
    out = []
    for m in range(motions):
        part = {}
        for s in layout.specs:
            key = copy_name(s.name, m) if s.role in STEP_ROLES else s.name
            if key in composed:
                part[s.name] = composed[key]
        out.append(part)
    return out


def split_tokens(layout: Layout, composed: TokenBatch, motions: int) -> list[TokenBatch]:
    """Per-motion token sets of the model's layout from composed tokens."""
    v = split_values(layout, composed.values, motions)
    i = split_values(layout, composed.ids, motions)
    k = split_values(layout, composed.mask, motions)
    return [TokenBatch(v[m], i[m], k[m]) for m in range(motions)]


class ComposedModel(nn.Module):
    """A network over the composed layout of `motions` motions (see the module docstring).

    model: the `RoboDiT` (or anything with its call signature and ``layout``). Has the
    network's call signature; `layout` is the composed layout.
    """

    def __init__(self, model: nn.Module, motions: int):
        super().__init__()
        self.model = model
        self.motions = int(motions)
        self.base_layout: Layout = model.layout
        self.layout = composed_layout(self.base_layout, self.motions)
        self.prediction = getattr(model, "prediction", "eps")

    def _batch(self, composed: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Copies stacked motion-major along B: rows m * n .. (m + 1) * n - 1 are copy m."""
        parts = split_values(self.base_layout, composed, self.motions)
        return {s.name: torch.cat([p[s.name] for p in parts]) for s in self.base_layout.specs}

    def _attend(self, attend: torch.Tensor) -> torch.Tensor:
        """(n, N_composed) -> (n * M, N) in the model's sequence order."""
        offsets, start = {}, 0
        for s in self.layout.specs:
            offsets[s.name] = (start, start + s.length)
            start += s.length
        rows = []
        for m in range(self.motions):
            cols = []
            for s in self.base_layout.specs:
                key = copy_name(s.name, m) if s.role in STEP_ROLES else s.name
                a, b = offsets[key]
                cols.append(attend[:, a:b])
            rows.append(torch.cat(cols, dim=1))
        return torch.cat(rows)

    def forward(
        self,
        values: Mapping[str, torch.Tensor],
        ids: Mapping[str, torch.Tensor],
        noised: Mapping[str, torch.Tensor],
        time: torch.Tensor,
        attend: torch.Tensor | None = None,
        outputs: Iterable[str] | None = None,
    ) -> dict[str, torch.Tensor]:
        """Predicted noise per composed type (the network's arguments, composed)."""
        M = self.motions
        n = time.shape[0]
        wanted_composed = set(outputs) if outputs is not None else None
        base_wanted = None
        if wanted_composed is not None:
            base_wanted = [
                s.name for s in self.base_layout.specs if any(k.split(SEPARATOR)[0] == s.name for k in wanted_composed)
            ]
        eps = self.model(
            self._batch(values),
            self._batch(ids),
            self._batch(noised),
            time.repeat(M),
            None if attend is None else self._attend(attend),
            outputs=base_wanted,
        )
        out = {}
        for s in self.base_layout.specs:
            if s.name not in eps:
                continue
            e = eps[s.name].reshape(M, n, *eps[s.name].shape[1:])  # (M, n, L, D)
            if s.role in STEP_ROLES:
                for m in range(M):
                    out[copy_name(s.name, m)] = e[m]
            else:
                out[s.name] = e.mean(0)
        if wanted_composed is not None:
            out = {k: v for k, v in out.items() if k in wanted_composed}
        return out


__all__ = [
    "SEPARATOR",
    "ComposedModel",
    "compose_tokens",
    "composed_layout",
    "copy_name",
    "split_tokens",
    "split_values",
]
