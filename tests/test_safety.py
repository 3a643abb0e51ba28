"""The arm side's guard: whatever arrives, the applied reference stays near the posture,
moves no faster than the joints may, and a command breaking a limit is not applied."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dammrl_core.robot import RobotDescription
from dammrl_core.safety import ArmCaps, CommandFreshness, guard_command
from dammrl_core.state import JointCommand
from tests.conftest import HOME_Q

CAPS = ArmCaps(0.05, 2000.0, 200.0, max_relative_target_rad=0.15, speed_fraction=1.0)
KP, KD = np.full(6, 400.0), np.full(6, 30.0)


def _command(
    q_ref: np.ndarray, dq_ref: np.ndarray | None = None, kp: np.ndarray = KP
) -> JointCommand:
    dq = np.zeros(6) if dq_ref is None else dq_ref
    return JointCommand(q_ref, dq, np.zeros(6), kp, KD)


def test_a_command_near_the_posture_passes_unchanged(robot: RobotDescription) -> None:
    command = _command(HOME_Q + 0.05)  # a reference leading the arm, moving 1 rad/s
    guarded = guard_command(command, HOME_Q, HOME_Q + 0.04, 0.01, robot, CAPS)
    assert guarded.command is command and not guarded.clamped


def test_a_far_target_is_clamped_to_the_relative_cap_and_the_joint_speed(
    robot: RobotDescription,
) -> None:
    far = np.clip(HOME_Q + 1.0, robot.q_min, robot.q_max)
    guarded = guard_command(_command(far, np.full(6, 10.0)), HOME_Q, HOME_Q, 0.01, robot, CAPS)
    assert guarded.clamped and guarded.command is not None
    assert "rad/s beyond" in str(guarded.reason)  # which cap, by how much: the log says
    step = np.abs(guarded.command.q_ref - HOME_Q)
    assert np.all(step <= robot.dq_max * 0.01 + 1e-12)  # rate from the last reference
    assert np.all(np.abs(guarded.command.dq_ref) <= robot.dq_max)
    fast = guard_command(_command(far), HOME_Q, HOME_Q, 0.01, robot, CAPS)
    assert "from the last reference in 10 ms" in str(fast.reason)
    unrated = guard_command(_command(far), HOME_Q, None, 0.01, robot, CAPS)
    assert unrated.command is not None and "from the measured posture" in str(unrated.reason)
    np.testing.assert_allclose(np.abs(unrated.command.q_ref - HOME_Q).max(), 0.15)


def test_a_clamp_warns_only_when_it_changed_the_reference_notably(
    robot: RobotDescription,
) -> None:
    """The first command after a hold, answering the state the hold began at, may move the
    reference by the IK's tolerance in no robot time: clamped and counted, said at info
    (it was a warning in every healthy run); a controller's jump stays a warning."""
    import logging

    tiny = guard_command(_command(HOME_Q + 0.001), HOME_Q, HOME_Q, 0.0, robot, CAPS)
    assert tiny.clamped and tiny.change_rad == pytest.approx(0.001)
    assert tiny.log_level == logging.INFO
    jump = guard_command(_command(HOME_Q + 0.1), HOME_Q, HOME_Q, 0.01, robot, CAPS)
    assert jump.clamped and jump.log_level == logging.WARNING


def test_a_command_beyond_the_limits_or_the_gains_is_rejected(robot: RobotDescription) -> None:
    beyond = robot.q_max + 0.2
    assert guard_command(_command(beyond), HOME_Q, None, 0.01, robot, CAPS).command is None
    stiff = _command(HOME_Q, kp=np.full(6, 5000.0))
    rejected = guard_command(stiff, HOME_Q, None, 0.01, robot, CAPS)
    assert rejected.command is None and rejected.reason is not None and "kp 5000" in rejected.reason


def test_run_credentials_refuse_a_folder_others_may_write(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from services.common.security import CredentialsError, run_credentials

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "runtime"))
    folder = run_credentials(7447)
    assert folder.parent.stat().st_mode & 0o777 == 0o700
    folder.parent.chmod(0o777)  # as if another user had prepared it
    with pytest.raises(CredentialsError, match="not private to you"):
        run_credentials(7447)


def test_clamped_commands_are_all_counted_and_the_first_five_and_each_hundredth_logged() -> None:
    freshness = CommandFreshness(answerable=4)
    freshness.held(1.0)
    freshness.published(7, 1.035)
    lines = [freshness.clamp("the rate cap", 7) for _ in range(200)]
    logged = [n for n, line in enumerate(lines, 1) if line is not None]
    assert freshness.clamped == 200 and logged == [1, 2, 3, 4, 5, 100, 200]
    assert lines[0] == ("command #1 clamped: the rate cap; it answers a state 35 ms after the "
                        "reference in force")  # fmt: skip
