"""The RoboToken schema: every token type, its attributes, their sizes and encodings.

This module is the one place the token layout is defined (paper, appendix "RoboToken",
Table "RoboToken Schema"). Tokenizer, detokenizer, episode tokens and normalisation all
read it; nothing else hard-codes a width or an offset. `SCHEMA_VERSION` is stored with
every token file, dataset and checkpoint, and bumps whenever the layout below changes.

A token of type T is a float vector of width ``T.width``: its attributes, each encoded,
concatenated in the order listed. IDs used as positional embeddings (``T.ids``) are not
part of the vector; they travel beside it as integers.

Conventions the encoded values follow:

* Frames. Every link is one primitive geom with the link frame at the geom's frame, so
  geometry needs no offset (transform canonicalisation). A joint token holds the pose of
  its link in the joint frame at the reference configuration (``qpos = ref``); the joint
  frame's z axis is the hinge / slide axis. Of a joint's two tokens, ``joint order`` 1 is
  the one with the higher link ID, and the joint coordinate moves that link relative to
  the other (tokenized robots always give the child the higher ID).
* Rotations are row-major 3x3 matrices (9 values); decoding projects them onto SO(3).
* Ranges of ``(0, 0)`` mean "unlimited" (joint range, control range, force range).
* Link ID -1 is the ground (world); free / track link ID -1 means "not one".
"""

from __future__ import annotations

import operator
from dataclasses import dataclass, field
from enum import Enum

from tt.kernels.errors import TTError

#: Bump on any change to the layout below; stored with tokens, datasets and checkpoints.
SCHEMA_VERSION = 1

#: Value every attribute of a padding token has after normalisation to [-1, 1].
PAD_VALUE = -1.0

#: Offset of the log encodings: ``log(x + LOG_OFFSET)`` keeps zero encodable.
LOG_OFFSET = 0.01
#: Log offset of link masses [kg] and principal moments [kg m^2]. With 0.01, every moment
#: below ~1e-3 kg m^2 (most links of an arm) would encode within 0.1 of log(0.01): the model
#: could not tell them apart, and float32 tokens would hold them only to ~5e-5 relative.
#: With 1e-4 both problems move below 1e-5 kg m^2.
MASS_LOG_OFFSET = 1e-4

# ---------------------------------------------------------------- enumerations (binary codes)
#: Link geometry codes. "none" is a link without geometry (a site, an intermediate frame of
#: a multi-joint body, or a body that only has an inertial).
GEOM_TYPES = ("none", "sphere", "capsule", "ellipsoid", "cylinder", "box")
#: Contact codes: 0 = the geom takes no part in contacts, else the MuJoCo ``condim``.
CONTACT_CONDIMS = (0, 1, 3, 4, 6)
#: Dynamic joint codes (ball joints have their own token type).
JOINT_TYPES = ("hinge", "slide")
#: Actuator codes: position servo (kp, kv), velocity servo (kv), motor (gear only).
ACTUATOR_TYPES = ("position", "velocity", "motor")

# ---------------------------------------------------------------- bit widths
LINK_ID_BITS = 7  # link IDs -1 (ground) .. 126
JOINT_ID_BITS = 6  # dynamic joint IDs an actuator can point to: 0 .. 63
FREE_LINK_ID_BITS = 1  # free link IDs -1 (none) .. 0
TRACK_LINK_ID_BITS = 2  # track link IDs -1 (none) .. 2
GEOM_TYPE_BITS = 3
CONTACT_BITS = 3
JOINT_TYPE_BITS = 2
ACTUATOR_TYPE_BITS = 2

#: Largest number of entities one robot may have, from the bit widths above.
MAX_LINKS = 2**LINK_ID_BITS - 1
MAX_DYNA_JOINTS = 2**JOINT_ID_BITS
MAX_FREE_LINKS = 2**FREE_LINK_ID_BITS - 1
MAX_TRACK_LINKS = 2**TRACK_LINK_ID_BITS - 1


class Encoding(Enum):
    """How an attribute's raw value becomes token values.

    NONE: as is. BINARY: an integer ``v`` as ``bits`` bits of ``v + offset``, most
    significant first (the offset makes -1, "none", encodable). LOG: ``log(x + 0.01)``
    (``Attribute.log_offset``; 1e-4 for masses and inertias). SIGNED_LOG: each value as
    ``[log(|x| + 0.01), 1 if x < 0 else 0]``. ROTATION: a 3x3
    matrix as its 9 row-major values, as is; decoding projects to the nearest rotation.
    """

    NONE = "none"
    BINARY = "binary"
    LOG = "log"
    SIGNED_LOG = "signed_log"
    ROTATION = "rotation"


class Role(str, Enum):
    """What a token type is, to the tokenizer and to the diffusion tasks (`tt.dit.tasks`).

    EMBODIMENT: time-invariant robot tokens (links, joints, actuators); diffused by the
    motion-to-robot task, clean for control. DYNAMICS: per-step state tokens (track-link
    poses, joint and actuator observations); diffused by motion-to-robot, and for control
    the window's earliest step is the clean current state. ACTION: per-step controller
    commands; diffused by both tasks. CONDITION: target poses; never noised. Every role but
    EMBODIMENT has a time ID (`STEP_ROLES`).
    """

    EMBODIMENT = "embodiment"
    DYNAMICS = "dynamics"
    ACTION = "action"
    CONDITION = "condition"


#: Roles with a time ID, tokenized once per control step.
STEP_ROLES = (Role.DYNAMICS, Role.ACTION, Role.CONDITION)


@dataclass(frozen=True)
class Attribute:
    """One attribute of a token type.

    name: attribute name; dim: number of raw values; encoding: see `Encoding`;
    bits: bits per value (BINARY only); offset: added before binary encoding (BINARY only);
    unit: SI unit of the raw values ("" for codes and IDs); log_offset: the offset of LOG
    and SIGNED_LOG encodings.
    """

    name: str
    dim: int
    encoding: Encoding = Encoding.NONE
    bits: int = 0
    offset: int = 0
    unit: str = ""
    log_offset: float = LOG_OFFSET

    def __post_init__(self) -> None:
        if self.dim < 1:
            raise ValueError(f"attribute {self.name!r}: dim must be >= 1, got {self.dim}")
        if self.encoding is Encoding.BINARY and (self.bits < 1 or self.dim != 1):
            raise ValueError(f"attribute {self.name!r}: binary attributes are one integer of >= 1 bits")
        if self.encoding is Encoding.ROTATION and self.dim != 9:
            raise ValueError(f"attribute {self.name!r}: rotations have dim 9, got {self.dim}")

    @property
    def width(self) -> int:
        """Number of token values the attribute occupies once encoded."""
        if self.encoding is Encoding.BINARY:
            return self.bits
        if self.encoding is Encoding.SIGNED_LOG:
            return 2 * self.dim
        return self.dim

    @property
    def low(self) -> int:
        """Smallest integer a BINARY attribute can hold."""
        return -self.offset

    @property
    def high(self) -> int:
        """Largest integer a BINARY attribute can hold."""
        return 2**self.bits - 1 - self.offset


@dataclass(frozen=True)
class TokenType:
    """One token type: attributes (in token order) and the names of its integer IDs."""

    name: str
    role: Role
    attributes: tuple[Attribute, ...]
    ids: tuple[str, ...]
    doc: str = ""
    _slices: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        start = 0
        for a in self.attributes:
            self._slices[a.name] = slice(start, start + a.width)
            start += a.width

    @property
    def width(self) -> int:
        """Width of one encoded token."""
        return sum(a.width for a in self.attributes)

    def attribute(self, name: str) -> Attribute:
        for a in self.attributes:
            if a.name == name:
                return a
        raise KeyError(
            f"token type {self.name!r} has no attribute {name!r}; attributes: {[a.name for a in self.attributes]}"
        )

    def slice(self, name: str) -> slice:
        """Where attribute `name` sits in the encoded token vector."""
        if name not in self._slices:
            raise KeyError(f"token type {self.name!r} has no attribute {name!r}; attributes: {list(self._slices)}")
        return self._slices[name]


def _pose_attrs() -> tuple[Attribute, ...]:
    return (Attribute("pos", 3, unit="m"), Attribute("rot", 9, Encoding.ROTATION))


def _joint_attrs(link_bits: int) -> tuple[Attribute, ...]:
    return (
        Attribute("type", 1, Encoding.BINARY, bits=JOINT_TYPE_BITS),
        Attribute("range", 2, unit="rad or m"),
        Attribute("armature", 1, Encoding.LOG, unit="kg m^2 or kg"),
        Attribute("damping", 1, Encoding.LOG, unit="N m s/rad or N s/m"),
        Attribute("frictionloss", 1, Encoding.LOG, unit="N m or N"),
        Attribute("stiffness", 1, Encoding.LOG, unit="N m/rad or N/m"),
        Attribute("springref", 1, unit="rad or m"),
        Attribute("ref", 1, unit="rad or m"),
        Attribute("pos", 3, unit="m"),
        Attribute("rot", 9, Encoding.ROTATION),
        Attribute("link_id", 1, Encoding.BINARY, bits=link_bits, offset=1),
    )


LINK = TokenType(
    "link",
    Role.EMBODIMENT,
    (
        Attribute("geom_type", 1, Encoding.BINARY, bits=GEOM_TYPE_BITS),
        Attribute("size", 3, unit="m"),
        Attribute("mass", 1, Encoding.LOG, unit="kg", log_offset=MASS_LOG_OFFSET),
        Attribute("ipos", 3, unit="m"),
        Attribute("irot", 9, Encoding.ROTATION),
        Attribute("inertia", 3, Encoding.LOG, unit="kg m^2", log_offset=MASS_LOG_OFFSET),
        Attribute("friction", 3),
        Attribute("contact", 1, Encoding.BINARY, bits=CONTACT_BITS),
        Attribute("rgba", 4),
        Attribute("free_id", 1, Encoding.BINARY, bits=FREE_LINK_ID_BITS, offset=1),
        Attribute("track_id", 1, Encoding.BINARY, bits=TRACK_LINK_ID_BITS, offset=1),
    ),
    ids=("link",),
    doc="One primitive: geometry (MuJoCo size convention), mass, inertial frame in the link "
    "frame (ipos, irot) with principal moments, friction, contact code, colour, and whether "
    "it is a free (floating-base) link or a track (end-effector) link.",
)

DYNA_JOINT = TokenType(
    "dyna_joint",
    Role.EMBODIMENT,
    _joint_attrs(LINK_ID_BITS),
    ids=("joint", "order"),
    doc="Half of a hinge or slide joint: the joint's parameters and the pose of one of its two "
    "links in the joint frame.",
)

BALL_JOINT = TokenType(
    "ball_joint",
    Role.EMBODIMENT,
    _joint_attrs(LINK_ID_BITS),
    ids=("joint", "order"),
    doc="Half of a ball joint (same layout as dyna_joint; range is (0, max angle)). Ball "
    "joints that close a kinematic loop stand for MuJoCo `connect` equalities.",
)

FIXED_JOINT = TokenType(
    "fixed_joint",
    Role.EMBODIMENT,
    (*_pose_attrs(), Attribute("link_id", 1, Encoding.BINARY, bits=LINK_ID_BITS, offset=1)),
    ids=("joint", "order"),
    doc="Half of a rigid connection: the pose of one of its two links in the joint frame.",
)

ACTUATOR = TokenType(
    "actuator",
    Role.EMBODIMENT,
    (
        Attribute("ctrlrange", 2, unit="rad, m, rad/s, m/s or N m"),
        Attribute("forcerange", 2, Encoding.SIGNED_LOG, unit="N m or N"),
        Attribute("kp", 1, Encoding.LOG, unit="N m/rad or N/m"),
        Attribute("kv", 1, Encoding.LOG, unit="N m s/rad or N s/m"),
        Attribute("gear", 1),
        Attribute("type", 1, Encoding.BINARY, bits=ACTUATOR_TYPE_BITS),
        Attribute("joint_id", 1, Encoding.BINARY, bits=JOINT_ID_BITS),
    ),
    ids=("actuator",),
    doc="A joint actuator: control and force limits, servo gains, gear, type and the dynamic joint it drives.",
)

FREE_LINK_OBS = TokenType(
    "free_link_obs",
    Role.DYNAMICS,
    _pose_attrs(),
    ids=("free_link", "time"),
    doc="World pose of a free link at one control step.",
)

TRACK_LINK_OBS = TokenType(
    "track_link_obs",
    Role.DYNAMICS,
    _pose_attrs(),
    ids=("track_link", "time"),
    doc="World pose of a track link (end effector) at one control step.",
)

DYNA_JOINT_OBS = TokenType(
    "dyna_joint_obs",
    Role.DYNAMICS,
    (Attribute("qpos", 1, unit="rad or m"), Attribute("qvel", 1, unit="rad/s or m/s")),
    ids=("joint", "time"),
    doc="Position and velocity of a hinge or slide joint at one control step.",
)

BALL_JOINT_OBS = TokenType(
    "ball_joint_obs",
    Role.DYNAMICS,
    (Attribute("quat", 4), Attribute("angvel", 3, unit="rad/s")),
    ids=("joint", "time"),
    doc="Orientation (w, x, y, z with w >= 0) and local angular velocity of a ball joint.",
)

ACTUATOR_OBS = TokenType(
    "actuator_obs",
    Role.DYNAMICS,
    (Attribute("velocity", 1, unit="rad/s or m/s"), Attribute("force", 1, unit="N m or N")),
    ids=("actuator", "time"),
    doc="Actuator velocity and force at one control step.",
)

CONTROL = TokenType(
    "control",
    Role.ACTION,
    (Attribute("target", 1, unit="rad or m"),),
    ids=("actuator", "time"),
    doc="The (clean) controller command of one actuator at one control step.",
)

TARGET_POSE = TokenType(
    "target_pose",
    Role.CONDITION,
    _pose_attrs(),
    ids=("track_link", "time"),
    doc="Target world pose of a track link at one control step.",
)


@dataclass(frozen=True)
class Schema:
    """All token types of one schema version, by name."""

    version: int
    types: tuple[TokenType, ...]

    def __getitem__(self, name: str) -> TokenType:
        for t in self.types:
            if t.name == name:
                return t
        raise KeyError(f"no token type {name!r} in schema v{self.version}; types: {self.names()}")

    def names(self, role: Role | None = None) -> tuple[str, ...]:
        return tuple(t.name for t in self.types if role is None or t.role is role)

    def to_dict(self) -> dict:
        """JSON-ready description, stored next to data so a reader can check the layout."""
        return {
            "version": self.version,
            "types": {
                t.name: {
                    "role": t.role.value,
                    "ids": list(t.ids),
                    "attributes": [
                        {
                            "name": a.name,
                            "dim": a.dim,
                            "width": a.width,
                            "encoding": a.encoding.value,
                            "bits": a.bits,
                            "offset": a.offset,
                            "log_offset": a.log_offset,
                            "unit": a.unit,
                        }
                        for a in t.attributes
                    ],
                }
                for t in self.types
            },
        }


SCHEMA = Schema(
    SCHEMA_VERSION,
    (
        LINK,
        DYNA_JOINT,
        BALL_JOINT,
        FIXED_JOINT,
        ACTUATOR,
        FREE_LINK_OBS,
        TRACK_LINK_OBS,
        DYNA_JOINT_OBS,
        BALL_JOINT_OBS,
        ACTUATOR_OBS,
        CONTROL,
        TARGET_POSE,
    ),
)

EMBODIMENT_TYPES = SCHEMA.names(Role.EMBODIMENT)


class SchemaVersionError(TTError):
    """Tokens, statistics or a checkpoint written with another schema version."""


def check_version(version: int, what: str) -> None:
    """Raise `SchemaVersionError` unless `version` is this code's `SCHEMA_VERSION` (an integer)."""
    try:
        if isinstance(version, bool):
            raise TypeError
        version = operator.index(version)  # ints, numpy integers and 0-d integer arrays
    except TypeError:
        raise SchemaVersionError(
            f"{what} has schema_version {version!r}, which is not an integer; this code reads "
            f"RoboToken schema {SCHEMA_VERSION}"
        ) from None
    if int(version) != SCHEMA_VERSION:
        raise SchemaVersionError(
            f"{what} uses RoboToken schema v{int(version)}, this code reads v{SCHEMA_VERSION}; "
            "re-tokenize the data with this version"
        )
