"""Servo figures from public datasheets, and the joint model tt builds from them.

A position-controlled DC servo cannot give its stall torque at speed: with the supply
voltage saturated, the motor's torque falls linearly from the stall torque at rest to zero
at the no-load speed (back-EMF). tt models one servo joint as

    tau = clamp(kp (q_cmd - q) - kv qd, -stall, stall) - (stall / no_load_speed) qd

which MuJoCo (and tt's kernels, which follow it) represent exactly as a force-limited
position actuator plus joint damping ``stall / no_load_speed``: the clamp is the voltage
limit and the damping term is the back-EMF, present whether or not the servo saturates.
Both are integrated as MuJoCo integrates them (joint damping implicitly), so the oracle and
the batched kernels stay in step. A joint of `count` servos geared together (the
ViperX 300 S doubles its shoulder and elbow) has `count` times the torque and the damping
at the same no-load speed.

Figures are the ROBOTIS e-Manual datasheet values at 12.0 V, the supply of the ViperX 300 S.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

RPM = 2.0 * math.pi / 60.0


@dataclass(frozen=True)
class Servo:
    """One servo model: stall torque [N m] and no-load speed [rad/s] at its rated voltage."""

    name: str
    stall_torque: float
    no_load_speed: float

    @property
    def back_emf_damping(self) -> float:
        """Torque lost per unit speed with the voltage saturated [N m s/rad]."""
        return self.stall_torque / self.no_load_speed


#: ROBOTIS Dynamixel XM540-W270: 10.6 N m stall (12.0 V, 4.4 A), 30 rpm no load (12.0 V).
XM540_W270 = Servo("XM540-W270", 10.6, 30.0 * RPM)
#: ROBOTIS Dynamixel XM430-W350: 4.1 N m stall (12.0 V, 2.3 A), 46 rpm no load (12.0 V).
XM430_W350 = Servo("XM430-W350", 4.1, 46.0 * RPM)


@dataclass(frozen=True)
class ServoJoint:
    """`count` servos of one model driving one joint."""

    servo: Servo
    count: int = 1

    @property
    def force(self) -> float:
        """Actuator force limit [N m]: the joint's stall torque."""
        return self.servo.stall_torque * self.count

    @property
    def damping(self) -> float:
        """Back-EMF damping of the joint [N m s/rad]."""
        return self.servo.back_emf_damping * self.count

    @property
    def no_load_speed(self) -> float:
        """Fastest the joint turns unloaded [rad/s]."""
        return self.servo.no_load_speed


__all__ = ["RPM", "Servo", "ServoJoint", "XM430_W350", "XM540_W270"]
