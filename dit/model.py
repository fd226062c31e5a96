"""The diffusion transformer over RoboTokens (paper §2.2, appendix "Transformer Transformer").

One sequence per sample: every token type of the `Layout`, padded to its length and
concatenated in layout order. A token's input vector is

    in_proj[type](value) + type_embed[type] + noised_embed[noised] + sum_k id_embed[kind_k](id_k)

a type-specific linear projection of its (normalised, possibly noised) value plus learned
embeddings of its token type, of whether it is being denoised or is clean conditioning
(this flag is how one network tells the tasks apart, "the task as a mask"), and of each
of its IDs (link, joint, joint order, actuator, free link, track link, time step; time
steps through sinusoidal features by default, `TimeIdEmbedder`). ID embeddings are shared
across types, so a joint token's link ID and a link token's own ID
land on the same embedding. A stack of DiT blocks with adaLN-Zero conditioning on the
diffusion time follows, then a per-type output head (adaLN-modulated LayerNorm and a
linear map) predicts each token's noise epsilon.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Iterable, Mapping

import torch
import torch.nn as nn
import torch.nn.functional as F

from tt.dit.anchors import Anchor
from tt.dit.layout import Layout, LayoutError
from tt.kernels.errors import TTError
from tt.tokens.schema import Role

#: Ways to embed time-step IDs (`DiTConfig.time_ids`).
TIME_ID_EMBEDDINGS = ("sinusoidal", "learned")


@dataclass(frozen=True)
class DiTConfig:
    """Backbone size. hidden: token width; depth: DiT blocks; heads: attention heads;
    mlp_ratio: MLP width / hidden; freq_dim: sinusoidal features of the diffusion time;
    time_ids: how a token's time-step ID is embedded, "sinusoidal" (`TimeIdEmbedder`) or
    "learned" (a lookup table like every other ID kind, as checkpoints before the choice)."""

    hidden: int = 256
    depth: int = 8
    heads: int = 4
    mlp_ratio: float = 4.0
    freq_dim: int = 256
    time_ids: str = "sinusoidal"

    def __post_init__(self) -> None:
        if self.time_ids not in TIME_ID_EMBEDDINGS:
            raise TTError(f"time_ids {self.time_ids!r} does not exist; choices: {list(TIME_ID_EMBEDDINGS)}")
        if self.hidden % self.heads:
            raise TTError(f"hidden {self.hidden} must be a multiple of heads {self.heads}")
        if self.depth < 1 or self.freq_dim < 2 or self.freq_dim % 2:
            raise TTError(
                f"depth must be >= 1 and freq_dim even >= 2, got depth={self.depth}, freq_dim={self.freq_dim}"
            )


#: Size variants: the paper's small (256 hidden, 8 layers, 4 heads) and large (512, 12, 8)
#: models, a tiny one for tests, and a mini one (128, 4, 4) that a 2-core CPU trains in an
#: hour: the shipped checkpoint's size.
DIT_CONFIGS: dict[str, DiTConfig] = {
    "tiny": DiTConfig(hidden=64, depth=2, heads=4, freq_dim=64),
    "mini": DiTConfig(hidden=128, depth=4, heads=4, freq_dim=128),
    "small": DiTConfig(hidden=256, depth=8, heads=4),
    "large": DiTConfig(hidden=512, depth=12, heads=8),
}


def get_config(size: str) -> DiTConfig:
    if size not in DIT_CONFIGS:
        raise TTError(f"model size {size!r} does not exist; sizes: {list(DIT_CONFIGS)}")
    return DIT_CONFIGS[size]


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """adaLN: x (B, N, H) scaled and shifted per sample by (B, H) vectors."""
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


class TimestepEmbedder(nn.Module):
    """Diffusion time u in (0, 1] (B,) -> (B, H): sinusoids of 1000 u, then a 2-layer MLP."""

    def __init__(self, hidden: int, freq_dim: int):
        super().__init__()
        self.freq_dim = freq_dim
        self.mlp = nn.Sequential(nn.Linear(freq_dim, hidden), nn.SiLU(), nn.Linear(hidden, hidden))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        half = self.freq_dim // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=u.device, dtype=torch.float32) / half)
        # 1000 u puts the T-step noise levels on the integer grid the frequencies were made for.
        args = 1000.0 * u.float().unsqueeze(1) * freqs  # (B, half)
        feats = torch.cat([torch.cos(args), torch.sin(args)], dim=1)  # (B, freq_dim)
        return self.mlp(feats.to(self.mlp[0].weight.dtype))  # (B, H)


class TimeIdEmbedder(nn.Module):
    """Time-step IDs (..., ) int64 -> (..., H): sinusoids of the step, then a linear map.

    A window holds 8 of an episode's up to `max_time` steps, so a lookup table sees each
    row in a small share of the windows and starts as noise (N(0, 0.02)): matching a
    dynamics token to the target of the same step, the first thing the model has to do,
    waits for every row to be learned. Sinusoids (the transformer's positional encoding,
    periods 2 pi to 2 pi x 10^4 steps) give every step a feature vector from the start, with
    equal steps most alike and nearby steps alike.
    """

    def __init__(self, hidden: int):
        super().__init__()
        half = hidden // 2
        self.register_buffer(
            "freqs", torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / half), persistent=False
        )
        self.proj = nn.Linear(2 * half, hidden)

    def forward(self, ids: torch.Tensor) -> torch.Tensor:
        args = ids.to(self.freqs.dtype).unsqueeze(-1) * self.freqs  # (..., half)
        return self.proj(torch.cat([torch.cos(args), torch.sin(args)], dim=-1).to(self.proj.weight.dtype))


class Attention(nn.Module):
    """Multi-head self-attention with an optional key mask (True = may be attended to)."""

    def __init__(self, hidden: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(hidden, 3 * hidden)
        self.proj = nn.Linear(hidden, hidden)

    def forward(self, x: torch.Tensor, key_mask: torch.Tensor | None) -> torch.Tensor:
        b, n, h = x.shape
        q, k, v = (
            self.qkv(x).reshape(b, n, 3, self.heads, h // self.heads).permute(2, 0, 3, 1, 4)
        )  # 3 x (B, heads, N, h/heads)
        mask = None if key_mask is None else key_mask[:, None, None, :]  # (B, 1, 1, N)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)  # (B, heads, N, h/heads)
        return self.proj(y.transpose(1, 2).reshape(b, n, h))  # (B, N, H)


class DiTBlock(nn.Module):
    """Pre-norm transformer block whose norms are modulated (shift, scale, gate) by the condition."""

    def __init__(self, hidden: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(hidden, elementwise_affine=False, eps=1e-6)
        self.attn = Attention(hidden, heads)
        self.norm2 = nn.LayerNorm(hidden, elementwise_affine=False, eps=1e-6)
        width = int(hidden * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(hidden, width), nn.GELU(approximate="tanh"), nn.Linear(width, hidden))
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(hidden, 6 * hidden))

    def forward(self, x: torch.Tensor, c: torch.Tensor, key_mask: torch.Tensor | None) -> torch.Tensor:
        shift1, scale1, gate1, shift2, scale2, gate2 = self.ada(c).chunk(6, dim=1)  # 6 x (B, H)
        x = x + gate1.unsqueeze(1) * self.attn(modulate(self.norm1(x), shift1, scale1), key_mask)  # (B, N, H)
        x = x + gate2.unsqueeze(1) * self.mlp(modulate(self.norm2(x), shift2, scale2))  # (B, N, H)
        return x


class OutputHead(nn.Module):
    """Per-type output: adaLN-modulated LayerNorm, then a linear map to the token width."""

    def __init__(self, hidden: int, dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(hidden, elementwise_affine=False, eps=1e-6)
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(hidden, 2 * hidden))
        self.linear = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        shift, scale = self.ada(c).chunk(2, dim=1)  # 2 x (B, H)
        return self.linear(modulate(self.norm(x), shift, scale))  # (B, L, D)


class RoboDiT(nn.Module):
    """Diffusion transformer over the token types of `layout` (see the module docstring).

    Output heads exist for every type that some task diffuses (all roles but condition).
    prediction: what the heads output, "eps", "x0" or "v" (`tt.dit.ddim.PREDICTIONS`; the
    sampler turns it into eps). anchors: anchored type -> `tt.dit.anchors.Anchor`, whose
    x0 prediction is the head's output plus the anchor (needs prediction "x0").
    """

    def __init__(
        self, layout: Layout, config: DiTConfig, *, prediction: str = "eps", anchors: Mapping[str, Anchor] | None = None
    ):
        super().__init__()
        from tt.dit.ddim import PREDICTIONS

        if prediction not in PREDICTIONS:
            raise TTError(f"prediction {prediction!r} does not exist; predictions: {list(PREDICTIONS)}")
        self.anchors = dict(anchors or {})
        if self.anchors and prediction != "x0":
            raise TTError(f"anchors act on the clean prediction: they need prediction 'x0', not {prediction!r}")
        for name, anchor in self.anchors.items():
            anchor.check(layout, name)
            base_roles = (Role.CONDITION,) if anchor.value is None else (Role.CONDITION, Role.DYNAMICS, Role.ACTION)
            if layout[name].role is Role.CONDITION or layout[anchor.on].role not in base_roles:
                raise LayoutError(
                    f"anchor {name!r} on {anchor.on!r}: a diffused type must be anchored on a condition "
                    "(or, by a state anchor, on the current state)"
                )
        self.layout = layout
        self.config = config
        self.prediction = prediction
        h = config.hidden
        self.in_proj = nn.ModuleDict({s.name: nn.Linear(s.dim, h) for s in layout.specs})
        kinds = sorted({k for s in layout.specs for k in s.ids})
        self.id_embed = nn.ModuleDict(
            {
                k: TimeIdEmbedder(h)
                if k == "time" and config.time_ids == "sinusoidal"
                else nn.Embedding(layout.id_sizes[k], h)
                for k in kinds
            }
        )
        self.type_embed = nn.Embedding(len(layout.specs), h)
        self.noised_embed = nn.Embedding(2, h)
        self.time_embed = TimestepEmbedder(h, config.freq_dim)
        self.blocks = nn.ModuleList([DiTBlock(h, config.heads, config.mlp_ratio) for _ in range(config.depth)])
        self.heads = nn.ModuleDict({s.name: OutputHead(h, s.dim) for s in layout.specs if s.role is not Role.CONDITION})
        for name, anchor in self.anchors.items():
            gain = anchor.gain if anchor.gain is not None else (1.0,) * len(anchor.scale)
            self.register_buffer(
                f"_anchor_{name}",
                torch.tensor([anchor.scale, anchor.offset, gain], dtype=torch.float32),
                persistent=False,
            )
        self.register_buffer(
            "_type_index",
            torch.cat([torch.full((s.length,), i, dtype=torch.long) for i, s in enumerate(layout.specs)]),
            persistent=False,
        )
        self.initialize_weights()

    def initialize_weights(self) -> None:
        """Xavier linears, N(0, 0.02) embeddings, and adaLN-Zero: every block's modulation and
        every head start at zero, so each block is the identity and every prediction 0 at init."""
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.Embedding):
                nn.init.normal_(m.weight, std=0.02)
        for lin in self.time_embed.mlp:
            if isinstance(lin, nn.Linear):
                nn.init.normal_(lin.weight, std=0.02)
        for block in self.blocks:
            nn.init.zeros_(block.ada[-1].weight)
            nn.init.zeros_(block.ada[-1].bias)
        for head in self.heads.values():
            nn.init.zeros_(head.ada[-1].weight)
            nn.init.zeros_(head.ada[-1].bias)
            nn.init.zeros_(head.linear.weight)
            nn.init.zeros_(head.linear.bias)

    def anchor_gain(self, name: str) -> torch.Tensor | None:
        """(D,) scale of anchored type `name`'s network output (`tt.dit.anchors.Anchor.gain`);
        None unless `name` is anchored with a gain."""
        anchor = self.anchors.get(name)
        if anchor is None or anchor.gain is None:
            return None
        return getattr(self, f"_anchor_{name}")[2]

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def embed(
        self, values: Mapping[str, torch.Tensor], ids: Mapping[str, torch.Tensor], noised: Mapping[str, torch.Tensor]
    ) -> torch.Tensor:
        """Token inputs (B, N, H) of the concatenated sequence."""
        parts = []
        for s in self.layout.specs:
            x = self.in_proj[s.name](values[s.name])  # (B, L, H)
            for k, kind in enumerate(s.ids):
                x = x + self.id_embed[kind](ids[s.name][..., k])  # (B, L, H)
            parts.append(x + self.noised_embed(noised[s.name].long()))  # (B, L, H)
        return torch.cat(parts, dim=1) + self.type_embed(self._type_index)  # (B, N, H)

    def forward(
        self,
        values: Mapping[str, torch.Tensor],
        ids: Mapping[str, torch.Tensor],
        noised: Mapping[str, torch.Tensor],
        time: torch.Tensor,
        attend: torch.Tensor | None = None,
        outputs: Iterable[str] | None = None,
    ) -> dict[str, torch.Tensor]:
        """Predicted noise (or x0, or v: `prediction`) per type.

        values: type -> (B, L, D) normalised values, noised where `noised` is True;
        ids: type -> (B, L, K) int64; noised: type -> (B, L) bool; time: (B,) diffusion
        time in (0, 1] (`CosineDDIM.model_time`); attend: (B, N) bool, False for tokens no
        token may attend to (masked padding), None to attend to all; outputs: types to
        predict (default: every type with a head). Returns type -> (B, L, D), the predicted
        eps, x0 or v (`prediction`).
        """
        x = self.embed(values, ids, noised)  # (B, N, H)
        c = self.time_embed(time)  # (B, H)
        for block in self.blocks:
            x = block(x, c, attend)  # (B, N, H)
        out, start = {}, 0
        wanted = set(self.heads.keys() if outputs is None else outputs)
        for s in self.layout.specs:
            if s.name in wanted:
                out[s.name] = self.heads[s.name](x[:, start : start + s.length], c)  # (B, L, D)
                if s.name in self.anchors:
                    scale, offset, gain = getattr(self, f"_anchor_{s.name}")  # 3 x (D,)
                    anchor = self.anchors[s.name]
                    base = anchor.base(self.layout, s.name, values[anchor.on])
                    out[s.name] = gain * out[s.name] + scale * base.to(scale.dtype) + offset
            start += s.length
        return out

    def describe(self) -> dict:
        """Layout and config, enough to rebuild the module (`from_description`)."""
        return {
            "layout": self.layout.to_dict(),
            "config": asdict(self.config),
            "prediction": self.prediction,
            "anchors": {n: a.to_dict() for n, a in self.anchors.items()},
        }

    @staticmethod
    def from_description(d: Mapping) -> "RoboDiT":
        # Checkpoints written before the prediction choice predict eps; those written before
        # the time-ID choice learned a table.
        config = DiTConfig(**{"time_ids": "learned", **d["config"]})
        anchors = {n: Anchor.from_dict(a) for n, a in (d.get("anchors") or {}).items()}
        return RoboDiT(Layout.from_dict(d["layout"]), config, prediction=d.get("prediction", "eps"), anchors=anchors)
