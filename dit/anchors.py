"""Anchors: a type's clean prediction as a residual from a conditioning type.

An end effector that tracks well sits near its target, so the network asked for a
track-link pose should not have to rebuild the target's pose from noise first. With an
anchor, the network's output for ``track_link_obs`` is added to the target pose of the same
slot (track link and step; the two types' slots line up, `Anchor.check`), carried into the
observation's normalised units: x0 = scale * target + offset + output. "Copy the target",
what most designs nearly do, is then the network's starting point (adaLN-Zero heads output
0), and what the model has to learn is the part the design decides: how far, and where,
the end effector falls behind or misses.

A state anchor does the same for commands: the network's output for ``control`` (the
joint-position command of actuator i at every step of the window) is added to the current
position of the joint actuator i drives, read from the window's first step of
``dyna_joint_obs`` (clean in the control task: the measured state). DiffIK's command is the
current position plus one IK increment, so "hold the current position" is the network's
starting point and what it learns is the increment: the delta actions of the issue's
recipe, without changing the tokens, the data or the normaliser. The increments are a few
hundredths of the command's normalised range (DiffIK moves a joint by about 0.06 rad a step
of a 2 pi range), so the network's output is scaled by their spread in the training data
(`Anchor.gain`): the head then regresses a target of unit size, as min-max normalised deltas
would be. (Measured on ViperX, `benchmarks/results/dit_control.md`: with or without the gain,
a mini model's commands stayed at their anchor for the first 500-1,500 steps; the gain is
kept for the target's scale, not for a measured gain in learning.) It
needs every actuator i to drive dynamic joint i (`check_joint_actuators`), as in the arm
spaces' position servos.

Anchors act on the clean prediction, so they need a network that predicts x0
(``prediction="x0"``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tt.dit.layout import Layout, LayoutError
from tt.kernels.errors import TTError
from tt.tokens.batch import TokenBatch
from tt.tokens.normalize import Normalizer

#: The anchors `pose_anchors` makes: anchored type -> the conditioning type it is a residual of.
POSE_ANCHORS = {"track_link_obs": "target_pose"}

#: The bases of `control_anchors`: name -> (type, value) of the window's first step that each
#: step's command is a residual of: the current joint position, or the last command (which
#: the control task must then be given: ``known_command``).
CONTROL_BASES = {"joints": ("dyna_joint_obs", 0), "command": ("control", 0)}


@dataclass(frozen=True)
class Anchor:
    """x0[type] = scale * base + offset + gain * network output, per value.

    on: the type the base is read from; scale, offset: (D,) maps of `on`'s normalised values
    into the anchored type's normalised units; value: None for a slot-for-slot anchor on a
    condition (base = values[on]), or k for a state anchor: slot i of every step of the
    anchored type takes value k of slot i of `on`'s first step (the window's current state);
    gain: (D,) scale of the network's output (None: 1), the residuals' spread.
    """

    on: str
    scale: tuple[float, ...]
    offset: tuple[float, ...]
    value: int | None = None
    gain: tuple[float, ...] | None = None

    def check(self, layout: Layout, name: str) -> None:
        """Raise LayoutError unless `name` and `on` are types of `layout` whose slots fit the anchor."""
        if name not in layout or self.on not in layout:
            raise LayoutError(
                f"anchor {name!r} on {self.on!r}: the layout lacks {[n for n in (name, self.on) if n not in layout]}"
            )
        a, b = layout[name], layout[self.on]
        if self.value is None:
            if (a.length, a.dim, a.per_step, a.ids) != (b.length, b.dim, b.per_step, b.ids):
                raise LayoutError(f"anchor {name!r} on {self.on!r}: their slots differ ({a} vs {b})")
        elif not (a.per_step and b.per_step and a.per_step <= b.per_step and 0 <= self.value < b.dim and a.dim == 1):
            raise LayoutError(
                f"anchor {name!r} on value {self.value} of {self.on!r}: needs two per-step types, one "
                f"value wide and with at most as many slots per step as {self.on!r} ({a} vs {b})"
            )
        if len(self.scale) != a.dim or len(self.offset) != a.dim or (self.gain is not None and len(self.gain) != a.dim):
            raise LayoutError(
                f"anchor {name!r} on {self.on!r}: {len(self.scale)} scales and {len(self.offset)} offsets "
                f"for {a.dim} values"
            )
        if self.gain is not None and not all(g > 0 for g in self.gain):
            raise LayoutError(f"anchor {name!r}: gains must be > 0, got {self.gain}")

    def base(self, layout: Layout, name: str, values: torch.Tensor) -> torch.Tensor:
        """What the anchored type's slots are residuals of, in `on`'s normalised units.

        values: (B, L_on, D_on), `on`'s values; returns (B, L, D) for the anchored type."""
        if self.value is None:
            return values
        a = layout[name]
        current = values[:, : a.per_step, self.value]  # (B, P): the first step's slots
        return current[:, None, :].expand(-1, layout.steps, -1).reshape(values.shape[0], a.length, 1)

    def to_dict(self) -> dict:
        d = {"on": self.on, "scale": list(self.scale), "offset": list(self.offset)}
        if self.value is not None:
            d["value"] = self.value
        if self.gain is not None:
            d["gain"] = list(self.gain)
        return d

    @staticmethod
    def from_dict(d: dict) -> "Anchor":
        value, gain = d.get("value"), d.get("gain")
        return Anchor(
            str(d["on"]),
            tuple(float(v) for v in d["scale"]),
            tuple(float(v) for v in d["offset"]),
            None if value is None else int(value),
            None if gain is None else tuple(float(g) for g in gain),
        )


def _affine(
    normalizer: Normalizer, name: str, on: str, dim: int, value: int | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """scale, offset (D,) of the map from `on`'s normalised values (value `value`, or all)
    to `name`'s: `on`'s denormalisation then `name`'s normalisation, both affine per value,
    so it is read off at -1 and +1."""
    width = dim if value is None else int(normalizer.low[on].shape[-1])
    ends = torch.tensor([[-1.0], [1.0]], dtype=torch.float64).expand(2, width)[:, None]  # (2, 1, W)
    raw = normalizer.denormalize_values(on, ends)
    if value is not None:
        raw = raw[..., value : value + 1]
    mapped = normalizer.normalize_values(name, raw)[:, 0]  # (2, D)
    return (mapped[1] - mapped[0]) / 2, (mapped[1] + mapped[0]) / 2


def pose_anchors(layout: Layout, normalizer: Normalizer) -> dict[str, Anchor]:
    """Track-link poses anchored on their targets (`POSE_ANCHORS`), for the types `layout` has.

    The map is the target's denormalisation followed by the observation's normalisation, both
    affine per value, so it is read off at -1 and +1.
    """
    out = {}
    for name, on in POSE_ANCHORS.items():
        if name not in layout or on not in layout:
            continue
        scale, offset = _affine(normalizer, name, on, layout[on].dim, None)
        out[name] = Anchor(on, tuple(scale.tolist()), tuple(offset.tolist()))
        out[name].check(layout, name)
    if not out:
        raise LayoutError(
            f"no anchor fits the layout: anchors need {POSE_ANCHORS}, the layout has {list(layout.names)}"
        )
    return out


def control_anchors(
    layout: Layout, normalizer: Normalizer, windows: TokenBatch | None = None, base: str = "joints"
) -> dict[str, Anchor]:
    """Commands anchored on the window's first step (`CONTROL_BASES`): the current positions
    of the joints they drive ("joints"), or the last command ("command").

    windows: raw (unnormalised) consecutive training windows, padded to `layout`; the gain is
    the root mean square of their residuals (command minus the anchor) in normalised units,
    per value. None: gain 1."""
    if base not in CONTROL_BASES:
        raise TTError(f"control anchor base {base!r} does not exist; bases: {', '.join(CONTROL_BASES)}")
    out = {}
    for name, (on, value) in {"control": CONTROL_BASES[base]}.items():
        if name not in layout or on not in layout:
            raise LayoutError(
                f"the control anchor needs types {name!r} and {on!r}; the layout has {list(layout.names)}"
            )
        scale, offset = _affine(normalizer, name, on, layout[name].dim, value)
        anchor = Anchor(on, tuple(scale.tolist()), tuple(offset.tolist()), value)
        anchor.check(layout, name)
        if windows is not None:
            target = normalizer.normalize_values(name, windows.values[name].double())
            start = anchor.base(layout, name, normalizer.normalize_values(on, windows.values[on].double()))
            res = (target - (scale * start + offset))[windows.mask[name]]  # (R, D) over real tokens
            if not len(res):
                raise LayoutError(f"the control anchor's gain needs real {name!r} tokens; the windows have none")
            gain = res.pow(2).mean(0).sqrt().clamp_min(1e-6)
            anchor = Anchor(on, anchor.scale, anchor.offset, value, tuple(gain.tolist()))
        out[name] = anchor
    return out


def check_joint_actuators(robots, models) -> None:
    """Raise LayoutError unless actuator i of every tokenized robot drives its dynamic joint i.

    robots: `tt.tokens.tokenize.RobotIndex` per design; models: their `mujoco.MjModel`s."""
    for d, (r, m) in enumerate(zip(robots, models)):
        driven = [int(m.actuator_trnid[a, 0]) for a in r.actuator_mj]
        if len(driven) > len(r.dyna_jnt) or any(j != int(r.dyna_jnt[i]) for i, j in enumerate(driven)):
            raise LayoutError(
                f"design {d}: its actuators drive MuJoCo joints {driven}, not its dynamic joints "
                f"{[int(j) for j in r.dyna_jnt]} in order; the control anchor needs actuator i on joint i"
            )


__all__ = ["Anchor", "CONTROL_BASES", "POSE_ANCHORS", "check_joint_actuators", "control_anchors", "pose_anchors"]
