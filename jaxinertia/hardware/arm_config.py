"""An arm's record on the bus: the driver's configuration and the safety limits taken from
an :class:`jaxinertia.arm.Arm` (bus IDs, baud rate, position-loop registers, motion timing,
joint limits and workspace box), so that nothing in :mod:`jaxinertia.hardware` holds a
particular arm's constants."""

from __future__ import annotations

from jaxinertia.arm import Arm
from jaxinertia.hardware.driver import ArmConfig
from jaxinertia.hardware.safety import SafetyLimits, default_joint_limits
from jaxinertia.robot import Robot

__all__ = ["arm_config", "safety_limits"]


def arm_config(arm: Arm, port: str, **overrides) -> ArmConfig:
    """The driver's configuration of ``arm``: its bus IDs and baud rate, the position-loop
    registers of its first joint's servo model (the record's gain override where it has
    one), its motion timing, and its joint limits (workspace widened by its safety margin)
    for the servos' own limit registers; ``overrides`` (ArmConfig's fields) win."""
    p, i, d = arm.gains[0] if arm.gains and arm.gains[0] else arm.servo_models[0].gains
    t = arm.timing
    values = dict(
        baudrate=arm.baudrate, joint_ids=tuple(arm.bus_ids), gripper_id=arm.gripper_id,
        p_gain=int(p), i_gain=int(i), d_gain=int(d),
        profile_velocity=t.profile_velocity, profile_acceleration=t.profile_acceleration,
        settle_time=t.settle_time, move_timeout=t.move_timeout,
        joint_limits=default_joint_limits(arm.workspace_deg, arm.safety_margin_deg))
    return ArmConfig(port=port, **{**values, **overrides})


def safety_limits(arm: Arm, robot: Robot) -> SafetyLimits:
    """``arm``'s safety limits: its workspace widened by ``safety_margin_deg``, the
    end-effector box by ``safety_box_margin_m`` (``robot``: its bare robot)."""
    return SafetyLimits.around_workspace(robot, workspace=arm.workspace_deg,
                                         margin_deg=arm.safety_margin_deg,
                                         box_margin=arm.safety_box_margin_m)
