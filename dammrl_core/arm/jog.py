"""Jog one joint of the real arm slowly, holding the others: any driver, any arm."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from dammrl_core.arm.driver import DriveCommand, Driver, DriverError
from dammrl_core.arm.settings import ArmSettings, arm_limits
from dammrl_core.arm.start import LATE_CYCLE_S, MotionClock, SoftStart, softened
from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotDescription


def jog(
    driver: Driver,
    robot: RobotDescription,
    settings: ArmSettings,
    joint: int,
    by_rad: float,
    speed_rad_s: float = 0.1,
    progress: Callable[[str], None] = print,
) -> float:
    """Move one joint by ``by_rad`` (clipped to its limits), slowly, holding the others;
    the measured motion [rad] (its sign checks the joint's direction)."""
    limits = arm_limits(robot, driver.joint_limits(robot), settings)
    arm = ArmModel(robot)
    kp, kd = np.array(settings.hold_kp_nm_per_rad), np.array(settings.hold_kd_nms_per_rad)
    period = 1.0 / settings.loop_rate_hz
    ramp = SoftStart.begin(settings.soft_start_s, settings.soft_start_fraction, LATE_CYCLE_S,
                           time.monotonic())  # fmt: skip

    def hold(q_ref: np.ndarray) -> DriveCommand:
        gravity = arm.inverse_dynamics(q_ref, np.zeros(6), np.zeros(6))
        law = DriveCommand(q_ref, np.zeros(6), gravity, kp, kd, limits.tau_max)
        return softened(law, ramp.share(time.monotonic()))

    try:
        driver.connect(hold=lambda state: hold(state.q_rad))
        q0 = driver.read_state().q_rad
        target = q0.copy()
        target[joint] = float(np.clip(q0[joint] + by_rad, limits.q_min[joint], limits.q_max[joint]))
        duration = max(0.5, 1.875 * abs(target[joint] - q0[joint]) / speed_rad_s)
        progress(f"joint {robot.joint_names[joint]}: {q0[joint]:+.3f} -> {target[joint]:+.3f} rad "
                 f"in {duration:.1f} s")  # fmt: skip
        clock, failures = MotionClock(LATE_CYCLE_S), 0  # a late cycle does not jump the move
        end = duration + 1.0 + settings.soft_start_s  # settle, after the soft start
        while (t := clock.advance(time.monotonic())) < end:
            s = min(max((t - settings.soft_start_s) / duration, 0.0), 1.0)
            q_ref = q0 + (10 * s**3 - 15 * s**4 + 6 * s**5) * (target - q0)
            failures = _cycle(driver, hold(q_ref), failures, settings.max_bus_errors)
            time.sleep(period)
        moved = float(driver.read_state().q_rad[joint] - q0[joint])
    finally:
        driver.disconnect()
    return moved


def _cycle(driver: Driver, law: DriveCommand, failures: int, allowed: int) -> int:
    """One read and write; a failed cycle leaves the servos on their last goal, ``allowed``
    in a row end the jog (the watchdog then stops the servos)."""
    try:
        driver.read_state()
        driver.write_command(law)
    except DriverError:
        if failures + 1 >= allowed:
            raise
        return failures + 1
    return 0
