"""Exponential moving average of model weights with power-law warm-up.

Update k (k = 1, 2, ... optimizer steps) sets, for every parameter p and its average a,

    a <- a + (1 - d_k) (p - a),   d_k = clip(1 - (1 + (k - 1) / inv_gamma)^(-power), min_decay, max_decay)

and d_1 = 0, so the first update copies the weights. This is the warm-up form of
diffusers' ``EMAModel`` (``use_ema_warmup=True``) with ``update_after_step=0``: with the
paper's power 0.75 and inv_gamma 1 the decay passes 0.99 after ~460 updates and 0.999
after ~10k, capped at max_decay 0.9999. (diffusers without ``use_ema_warmup`` ignores
the power and uses (1 + k) / (10 + k) instead.) Buffers are not averaged; the model has
no persistent ones.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import torch
import torch.nn as nn

from tt.kernels.errors import TTError


class EMA:
    """Shadow copy of a model's parameters (float32, same device) and the update count."""

    def __init__(
        self,
        model: nn.Module,
        *,
        power: float = 0.75,
        inv_gamma: float = 1.0,
        min_decay: float = 0.0,
        max_decay: float = 0.9999,
    ):
        if power <= 0 or inv_gamma <= 0 or not 0 <= min_decay <= max_decay < 1:
            raise TTError(
                f"need power > 0, inv_gamma > 0, 0 <= min_decay <= max_decay < 1; got power={power}, "
                f"inv_gamma={inv_gamma}, min_decay={min_decay}, max_decay={max_decay}"
            )
        self.power, self.inv_gamma, self.min_decay, self.max_decay = power, inv_gamma, min_decay, max_decay
        self.shadow = [p.detach().clone().float() for p in model.parameters()]
        self.updates = 0

    def decay(self, k: int) -> float:
        """d_k of the k-th update (k >= 1); 0 for the first."""
        step = k - 1
        if step <= 0:
            return 0.0
        d = 1.0 - (1.0 + step / self.inv_gamma) ** (-self.power)
        return min(max(d, self.min_decay), self.max_decay)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        w = 1.0 - self.decay(self.updates)
        params = list(model.parameters())
        if len(params) != len(self.shadow):
            raise ValueError(f"model has {len(params)} parameter tensors, the EMA {len(self.shadow)}")
        torch._foreach_lerp_(self.shadow, [p.detach().float() for p in params], w)

    @torch.no_grad()
    def copy_to(self, model: nn.Module) -> None:
        """Overwrite the model's parameters with the averages."""
        for a, p in zip(self.shadow, model.parameters()):
            p.copy_(a.to(p.dtype))

    @contextmanager
    def applied(self, model: nn.Module) -> Iterator[nn.Module]:
        """The model with EMA weights inside the block, its own weights restored after."""
        saved = [p.detach().clone() for p in model.parameters()]
        self.copy_to(model)
        try:
            yield model
        finally:
            with torch.no_grad():
                for s, p in zip(saved, model.parameters()):
                    p.copy_(s)

    def state_dict(self) -> dict:
        return {
            "shadow": [a.clone() for a in self.shadow],
            "updates": self.updates,
            "power": self.power,
            "inv_gamma": self.inv_gamma,
            "min_decay": self.min_decay,
            "max_decay": self.max_decay,
        }

    def load_state_dict(self, state: dict) -> None:
        if len(state["shadow"]) != len(self.shadow):
            raise TTError(f"EMA state has {len(state['shadow'])} tensors, this model {len(self.shadow)}")
        for a, b in zip(self.shadow, state["shadow"]):
            if a.shape != b.shape:
                raise TTError(f"EMA tensor of shape {tuple(b.shape)} does not fit parameter of shape {tuple(a.shape)}")
            a.copy_(b)
        self.updates = int(state["updates"])
        self.power, self.inv_gamma = float(state["power"]), float(state["inv_gamma"])
        self.min_decay, self.max_decay = float(state["min_decay"]), float(state["max_decay"])
