"""Checks made before every move: joint limits and a workspace box for the end effector."""

from __future__ import annotations

from dataclasses import dataclass

import jax
import numpy as np

from jaxinertia.errors import UsageError
from jaxinertia.kinematics import ee_pose, ee_positions
from jaxinertia.robot import Robot

__all__ = ["SafetyError", "SafetyLimits", "default_joint_limits"]

_DEG = np.pi / 180.0


class SafetyError(UsageError):
    """A goal that must not be commanded; raised before anything is written to a servo
    (exit code 2: the request is refused, the arm has not moved)."""


def default_joint_limits(workspace_deg, margin_deg: float = 8.0) -> np.ndarray:
    """(N, 2) [rad]: the arm's workspace ``workspace_deg`` (``(lo, hi)`` per joint [deg],
    :attr:`jaxinertia.arm.Arm.workspace_deg`) widened by ``margin_deg`` (the record's
    ``safety_margin_deg``; 8 deg covers the 3 deg pre-positions with room to spare)."""
    w = np.asarray(workspace_deg, np.float64)
    return (w + np.array([-margin_deg, margin_deg])) * _DEG


@dataclass(frozen=True)
class SafetyLimits:
    """Joint limits (N, 2) [rad] and an axis-aligned box (2, 3) for the end-effector origin
    in the base frame [m] (None: no workspace check)."""

    joint_limits: np.ndarray
    ee_box: np.ndarray | None = None

    @classmethod
    def around_workspace(cls, robot: Robot, *, workspace, margin_deg: float = 8.0,
                         box_margin: float = 0.03) -> SafetyLimits:
        """Joint limits around the arm's ``workspace`` [deg]; the end-effector box is what
        those joint limits reach (corners and a grid) plus ``box_margin`` on every side."""
        limits = default_joint_limits(workspace, margin_deg)
        axes = [np.linspace(lo, hi, 5) for lo, hi in limits]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(limits))
        p = np.asarray(ee_positions(robot, grid))
        box = np.stack([p.min(0) - box_margin, p.max(0) + box_margin])
        return cls(limits, box)

    def check(self, q: np.ndarray, robot: Robot | None = None) -> None:
        """Raises :class:`SafetyError` unless every joint of ``q`` (N,) [rad] is within its
        limits and (with a box and a robot) the end effector is inside the box."""
        q = np.asarray(q, np.float64)
        lo, hi = self.joint_limits[:, 0], self.joint_limits[:, 1]
        if not np.all(np.isfinite(q)):
            raise SafetyError(f"goal {q} is not finite")
        bad = np.flatnonzero((q < lo) | (q > hi))
        if bad.size:
            j = int(bad[0])
            raise SafetyError(
                f"joint {j + 1} goal {np.degrees(q[j]):.2f} deg is outside its limits "
                f"[{np.degrees(lo[j]):.1f}, {np.degrees(hi[j]):.1f}] deg")
        if self.ee_box is not None and robot is not None:
            p = np.asarray(_ee_position(robot, q))
            if np.any(p < self.ee_box[0]) or np.any(p > self.ee_box[1]):
                raise SafetyError(f"end effector at {np.round(p, 3)} m would leave the "
                                  f"workspace box {np.round(self.ee_box, 3).tolist()} m")


@jax.jit
def _ee_position(robot: Robot, q):
    return ee_pose(robot, q)[1]
