"""Anchors: a type's clean prediction as a residual from a conditioning type.

An end effector that tracks well sits near its target, so the network asked for a
track-link pose should not have to rebuild the target's pose from noise first. With an
anchor, the network's output for ``track_link_obs`` is added to the target pose of the same
slot (track link and step; the two types' slots line up, `Anchor.check`), carried into the
observation's normalised units: x0 = scale * target + offset + output. "Copy the target",
what most designs nearly do, is then the network's starting point (adaLN-Zero heads output
0), and what the model has to learn is the part the design decides: how far, and where,
the end effector falls behind or misses.

Anchors act on the clean prediction, so they need a network that predicts x0
(``prediction="x0"``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tt.dit.layout import Layout, LayoutError
from tt.tokens.normalize import Normalizer

#: The anchors `pose_anchors` makes: anchored type -> the conditioning type it is a residual of.
POSE_ANCHORS = {"track_link_obs": "target_pose"}


@dataclass(frozen=True)
class Anchor:
    """x0[type] = scale * values[on] + offset + network output, per value.

    on: the conditioning type; scale, offset: (D,) maps of `on`'s normalised values into the
    anchored type's normalised units.
    """

    on: str
    scale: tuple[float, ...]
    offset: tuple[float, ...]

    def check(self, layout: Layout, name: str) -> None:
        """Raise LayoutError unless `name` and `on` are types of `layout` with equal slots."""
        if name not in layout or self.on not in layout:
            raise LayoutError(f"anchor {name!r} on {self.on!r}: the layout lacks {[n for n in (name, self.on) if n not in layout]}")
        a, b = layout[name], layout[self.on]
        if (a.length, a.dim, a.per_step, a.ids) != (b.length, b.dim, b.per_step, b.ids):
            raise LayoutError(f"anchor {name!r} on {self.on!r}: their slots differ ({a} vs {b})")
        if len(self.scale) != a.dim or len(self.offset) != a.dim:
            raise LayoutError(f"anchor {name!r} on {self.on!r}: {len(self.scale)} scales and {len(self.offset)} offsets "
                              f"for {a.dim} values")

    def to_dict(self) -> dict:
        return {"on": self.on, "scale": list(self.scale), "offset": list(self.offset)}

    @staticmethod
    def from_dict(d: dict) -> "Anchor":
        return Anchor(str(d["on"]), tuple(float(v) for v in d["scale"]), tuple(float(v) for v in d["offset"]))


def pose_anchors(layout: Layout, normalizer: Normalizer) -> dict[str, Anchor]:
    """Track-link poses anchored on their targets (`POSE_ANCHORS`), for the types `layout` has.

    The map is the target's denormalisation followed by the observation's normalisation, both
    affine per value, so it is read off at -1 and +1.
    """
    out = {}
    for name, on in POSE_ANCHORS.items():
        if name not in layout or on not in layout:
            continue
        ends = torch.tensor([[-1.0], [1.0]], dtype=torch.float64).expand(2, layout[on].dim)[:, None]  # (2, 1, D)
        mapped = normalizer.normalize_values(name, normalizer.denormalize_values(on, ends))[:, 0]  # (2, D)
        scale, offset = (mapped[1] - mapped[0]) / 2, (mapped[1] + mapped[0]) / 2
        out[name] = Anchor(on, tuple(scale.tolist()), tuple(offset.tolist()))
        out[name].check(layout, name)
    if not out:
        raise LayoutError(f"no anchor fits the layout: anchors need {POSE_ANCHORS}, the layout has {list(layout.names)}")
    return out


__all__ = ["Anchor", "POSE_ANCHORS", "pose_anchors"]
