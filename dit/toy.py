"""Synthetic tokenized episodes with structure, for tests and benchmarks of the DiT alone.

Robots of varying size (so every type has padding), whose per-step tokens are smooth
functions of time with frequencies and phases drawn from the robot's own embodiment
tokens, and targets that follow the same frequencies: enough coupling between
embodiment, dynamics and conditioning that a model has something to learn, without
running the simulator or the tokenizer.

IDs follow the RoboToken conventions: a type with an "order" ID holds two tokens per
entity (entity = position // 2, order = position % 2); other IDs are the entity's position.
"""

from __future__ import annotations

from typing import Mapping

import torch

from tt.dit.data import EpisodeTokens
from tt.dit.layout import layout_from_schema
from tt.tokens.schema import STEP_ROLES, Role

#: A small generic type set: name -> (dim, ids, role, tokens per robot or per step).
TOY_TYPES: dict[str, tuple[int, tuple[str, ...], Role, int]] = {
    "body": (5, ("link",), Role.EMBODIMENT, 4),
    "hinge": (4, ("joint", "order"), Role.EMBODIMENT, 6),
    "state": (2, ("joint", "time"), Role.DYNAMICS, 3),
    "command": (1, ("joint", "time"), Role.ACTION, 3),
    "target": (3, ("track_link", "time"), Role.CONDITION, 1),
}
TOY_ID_SIZES = {"link": 8, "joint": 8, "order": 2, "track_link": 2, "time": 128}


def _ids(ids: tuple[str, ...], length: int, sizes: Mapping[str, int]) -> torch.Tensor:
    pos = torch.arange(length)
    cols = []
    for kind in ids:
        if kind == "order":
            cols.append(pos % 2)
        elif kind == "time":
            cols.append(torch.zeros_like(pos))
        elif "order" in ids:
            cols.append((pos // 2).clamp(max=sizes[kind] - 1))
        else:
            cols.append(pos.clamp(max=sizes[kind] - 1))
    return torch.stack(cols, dim=-1)  # (length, K)


def toy_episodes(
    *,
    episodes: int = 32,
    steps: int = 32,
    seed: int = 0,
    schema_counts: Mapping[str, int] | None = None,
    max_time: int = 1024,
) -> EpisodeTokens:
    """E synthetic episodes of `steps` control steps (all full length).

    schema_counts: build RoboToken-schema types with these largest counts (see
    `tt.dit.layout.layout_from_schema`, whose ID sizes and `max_time` are used); None for
    the small `TOY_TYPES`.
    """
    g = torch.Generator().manual_seed(seed)
    if schema_counts is None:
        types = TOY_TYPES
        sizes = dict(TOY_ID_SIZES)
        version = None
    else:
        layout = layout_from_schema(schema_counts, steps=1, max_time=max_time)
        types = {s.name: (s.dim, s.ids, s.role, s.per_step or s.length) for s in layout.specs}
        sizes = dict(layout.id_sizes)
        version = layout.schema_version
    roles = {k: v[2] for k, v in types.items()}
    id_names = {k: v[1] for k, v in types.items()}
    # Robot size: a fraction in [0.5, 1] of every type's maximum count, at least one token.
    frac = 0.5 + 0.5 * torch.rand(episodes, generator=g)
    static_values, static_ids, static_mask = {}, {}, {}
    step_values, step_ids, step_mask = {}, {}, {}
    t = torch.arange(steps, dtype=torch.float32)
    embodiment_code = torch.zeros(episodes, 4)
    for name, (dim, ids, role, count) in types.items():
        n_real = (frac * count).ceil().long().clamp(1, count)  # (E,)
        real = torch.arange(count)[None, :] < n_real[:, None]  # (E, count)
        if role not in STEP_ROLES:
            v = torch.randn(episodes, count, dim, generator=g)
            if "order" in ids:
                v[:, 1::2] = v[:, 0::2][:, : v[:, 1::2].shape[1]]  # a joint's two tokens share parameters
            v = v * real[..., None]
            mix = torch.randn(dim, 4, generator=g) / dim**0.5
            embodiment_code += v.mean(1) @ mix  # a fixed random linear map of the mean token
            static_values[name], static_mask[name] = v, real
            static_ids[name] = _ids(ids, count, sizes).expand(episodes, count, len(ids)).clone()
    omega = 0.05 + 0.1 * torch.sigmoid(embodiment_code)  # (E, 4) rad/step
    phase = embodiment_code  # (E, 4)
    for name, (dim, ids, role, count) in types.items():
        if role in STEP_ROLES:
            n_real = (frac * count).ceil().long().clamp(1, count)
            real = torch.arange(count)[None, :] < n_real[:, None]  # (E, P)
            k = torch.arange(count * dim).reshape(count, dim) % 4  # which frequency each feature uses
            w = omega[:, k]  # (E, P, D)
            p = phase[:, k] + torch.arange(count * dim, dtype=torch.float32).reshape(count, dim)
            v = torch.sin(w[:, None] * t[None, :, None, None] + p[:, None])  # (E, S, P, D)
            if role is Role.CONDITION:
                v = 0.5 * v + 0.1 * torch.cos(p[:, None])
            step_values[name] = v * real[:, None, :, None]
            step_mask[name] = real
            step_ids[name] = _ids(ids, count, sizes).expand(episodes, count, len(ids)).clone()
    return EpisodeTokens(
        roles,
        id_names,
        sizes,
        static_values,
        static_ids,
        static_mask,
        step_values,
        step_ids,
        step_mask,
        torch.full((episodes,), steps, dtype=torch.long),
        version,
        tuple(types),
    )
