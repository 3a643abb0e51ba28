"""The robot service on the emulated arm: the real driver path (dynamixel-sdk, Protocol 2.0
on a pseudo-terminal, the MuJoCo arm behind the servos), its joint law, holds, homing,
the emergency stop and every injected fault: a stop or a hold, reported, no jump."""

from __future__ import annotations

import contextlib
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
import pytest

from dammrl.devices.emulators.arm import EmulatedArm, MujocoServos, emulated_arm, inject
from dammrl.devices.emulators.servo_chain import (
    BUTTON_MODEL,
    GOAL_POSITION,
    KD_UNIT_AS_PER_RAD,
    KP_UNIT_A_PER_RAD,
    POSITION_D_GAIN,
    POSITION_P_GAIN,
    TICKS_PER_RAD,
    TORQUE_ENABLE,
    XM430_W350,
)
from dammrl_core.arm.driver import BadReplyError, DriveCommand, DriveFault, DriverError, JointState
from dammrl_core.arm.dynamixel.calibration import Calibration, load_calibration, save_calibration
from dammrl_core.arm.dynamixel.driver import BUTTON_RANGE_UM, DynamixelDriver
from dammrl_core.arm.dynamixel.tools import guided_calibration, scan
from dammrl_core.arm.jog import jog
from dammrl_core.arm.settings import ArmSettings, arm_limits
from dammrl_core.arm.start import LATE_CYCLE_S, SoftStart
from dammrl_core.dynamics import ArmModel
from dammrl_core.errors import ConfigurationError
from dammrl_core.robot import RobotSettings
from dammrl_core.state import JointCommand as CoreCommand
from dammrl_core.task import TaskSettings, scene_layout
from schemas import (
    EmergencyStop,
    GoalRefused,
    Header,
    JointCommand,
    Message,
    RobotState,
    TaskGoal,
)
from services.robot.law import ArmLaw, Start
from services.robot.link import DriveLink
from services.robot.node import START_RETRIES, RobotNode, make_driver

CALIBRATION = Calibration(
    offsets_rad=(0.1, -0.05, 0.0, 0.2, 0.0, -0.1),
    directions=(1, -1, 1, -1, 1, 1),
    gear_ratios=(2.0, 1.0, 1.5, 1.0, 1.0, 1.0),
)


# ---- the calibration ----------------------------------------------------------------------
def test_calibration_frames_round_trip_and_refuse_limits_beyond_the_urdf(tmp_path: Path) -> None:
    q = np.array([0.3, 1.1, -0.2, 1.5, 0.4, -0.3])
    np.testing.assert_allclose(CALIBRATION.joint_rad(CALIBRATION.servo_rad(q)), q)
    np.testing.assert_allclose(CALIBRATION.to_rad(CALIBRATION.to_ticks(q)), q, atol=1 / 651)
    path = tmp_path / "arm.json"
    save_calibration(CALIBRATION, path)
    assert load_calibration(path) == CALIBRATION
    path.write_text('{"ids": [1, 1, 2, 3, 4, 5]}')
    with pytest.raises(ConfigurationError, match=r"arm calibration .*six different ids"):
        load_calibration(path)
    wide = Calibration(q_min_rad=(-2.0, -1, -1, 0, -1, -1), q_max_rad=(1, 1, 1, 1, 1, 1))
    with pytest.raises(ConfigurationError, match="not inside the URDF"):
        wide.limits(RobotSettings().load())


# ---- the driver on the emulated bus -------------------------------------------------------
@pytest.fixture()
def arm(tmp_path: Path) -> Iterator[EmulatedArm]:
    with emulated_arm(tmp_path / "ttyROBOT", CALIBRATION) as emulated:
        yield emulated


def test_the_servo_law_is_the_joint_law(arm: EmulatedArm) -> None:
    """Goal shift, P and D written by the driver make each servo's own law
    P (goal - angle) - D velocity equal tau_ff + kp (q_ref - q) + kd (dq_ref - dq)."""
    rng = np.random.default_rng(3)
    driver = DynamixelDriver(str(arm.bus.link), CALIBRATION)
    with driver:
        q_ref = driver.read_state().q_rad + rng.uniform(-0.05, 0.05, 6)
        command = DriveCommand(
            q_ref, rng.uniform(-0.3, 0.3, 6), rng.uniform(-5, 5, 6),
            np.array([400.0, 400, 200, 200, 50, 50]), np.array([30.0, 30, 12, 12, 1.5, 1.5]),
            np.full(6, 30.0),
        )  # fmt: skip
        driver.write_command(command)
        driver.read_state()  # answered after the write was taken up
        with arm.bus.lock:
            servos = [arm.chain.servos[i] for i in CALIBRATION.ids]
            goal = np.array([(s.value(GOAL_POSITION, 4) - 2048) / TICKS_PER_RAD for s in servos])
            p = np.array([s.value(POSITION_P_GAIN, 2) for s in servos]) * KP_UNIT_A_PER_RAD
            d = np.array([s.value(POSITION_D_GAIN, 2) for s in servos]) * KD_UNIT_AS_PER_RAD
    q, dq = q_ref + rng.uniform(-0.02, 0.02, 6), rng.uniform(-0.5, 0.5, 6)  # any state
    scale = np.asarray(CALIBRATION.directions) * np.asarray(CALIBRATION.gear_ratios)
    current = p * (goal - CALIBRATION.servo_rad(q)) - d * scale * dq
    servo_torque = CALIBRATION.joint_torque(current)
    law = command.tau_ff + command.kp * (q_ref - q) + command.kd * (command.dq_ref - dq)
    np.testing.assert_allclose(servo_torque, law, atol=0.02 * np.abs(law).max() + 0.05)


def test_the_servos_hold_with_the_law_given_from_their_torque_on(arm: EmulatedArm) -> None:
    """The torque went on with zero gains and the host wrote its law a cycle later: a
    host that stalled there left the arm limp (a free fall at start-up). The law is now
    written before the torque-on; with the host silent, the watchdog stops the servos and
    they keep its gains, whose damping holds a sagging joint below its speed limit."""
    robot = RobotSettings().load()
    settings = ArmSettings()
    gravity_of = ArmModel(robot).inverse_dynamics
    kp = np.array(settings.hold_kp_nm_per_rad) * settings.soft_start_fraction
    kd = np.array(settings.hold_kd_nms_per_rad)

    def hold(state: JointState) -> DriveCommand:
        tau = gravity_of(state.q_rad, np.zeros(6), np.zeros(6))
        return DriveCommand(state.q_rad, np.zeros(6), tau, kp, kd, robot.tau_max * 0.6)

    driver = DynamixelDriver(str(arm.bus.link), CALIBRATION)
    try:
        for _ in range(20):  # as the node retries: a loaded machine may time a packet out
            with contextlib.suppress(DriverError):
                driver.connect(hold=hold)
                break
        with arm.bus.lock:
            servos = [arm.chain.servos[i] for i in CALIBRATION.ids]
            assert all(s.torque_on for s in servos)
            assert all(s.value(POSITION_P_GAIN, 2) > 0 and s.value(POSITION_D_GAIN, 2) > 0
                       for s in servos)  # fmt: skip
        fastest, end = np.zeros(6), time.monotonic() + 1.0
        while time.monotonic() < end:  # the host silent: the servos on their own
            fastest = np.maximum(fastest, arm.joint_speeds())
            time.sleep(0.005)
        print(f"silent host after a torque-on at 10 % stiffness: fastest {np.round(fastest, 2)}")
        assert np.all(fastest < robot.dq_max * settings.speed_fraction), fastest
    finally:
        driver.disconnect()


def test_a_servo_started_beside_holding_ones_leaves_them_their_law(arm: EmulatedArm) -> None:
    """A connect that finds some servos holding (a retry, a servo back from a brown-out)
    starts the others only: the holding ones keep their stiffness (they neither drop, as
    when every torque went off to set the mode, nor soften with a soft start), and it
    counts as a reconnection (no soft start)."""
    stiff, soft = np.array([300.0, 300, 150, 150, 40, 40]), np.full(6, 4.0)

    def law(kp: np.ndarray) -> Callable[[JointState], DriveCommand]:
        return lambda state: DriveCommand(state.q_rad, np.zeros(6), np.zeros(6), kp, kp / 10,
                                          np.full(6, 30.0))  # fmt: skip

    driver = DynamixelDriver(str(arm.bus.link), CALIBRATION)
    gains = []
    try:
        for kp, held in ((stiff, False), (soft, True)):
            for _ in range(20):  # as the node retries: a loaded machine may lose a packet
                with contextlib.suppress(DriverError):
                    assert driver.connect(hold=law(kp)) is held
                    break
            with arm.bus.lock:
                gains.append([arm.chain.servos[i].value(POSITION_P_GAIN, 2)
                              for i in CALIBRATION.ids])  # fmt: skip
                arm.chain.servos[6].table[64] = 0  # servo 6 lost its torque (a brown-out)
    finally:
        driver.disconnect()
    first, second = gains
    assert second[:5] == first[:5], gains  # servos 1-5 kept their stiffness
    assert second[5] < first[5] / 3, gains  # servo 6 started with the soft law


@pytest.mark.parametrize("fault", ["short 1", "late 1"])
def test_a_short_or_late_status_packet_is_a_missed_read_not_a_crash(
    arm: EmulatedArm, fault: str
) -> None:
    """A status packet says nothing of what it answers: one a parameter short, or one that
    comes after the SDK stopped waiting (here: to the re-arm's one-byte read, which is
    tried again) is a bus error like a timeout or a retry, and the next read is whole.
    (It was ``struct.error: unpack requires a buffer of 10 bytes``: the service died.)"""
    driver = DynamixelDriver(str(arm.bus.link), CALIBRATION)
    with driver:
        q = driver.read_state().q_rad
        stiff = np.array([400.0, 400, 200, 200, 50, 50])
        driver.write_command(DriveCommand(q, np.zeros(6), np.zeros(6), stiff, stiff / 10,
                                          np.full(6, 30.0)))  # holding: a still arm  # fmt: skip
        time.sleep(0.3)
        inject(arm, fault)
        if fault.startswith("late"):
            # its answer comes too late: the read is tried again and takes it (a single
            # late answer is no failed re-arm); the retry's own answer is flushed
            assert driver.rearm() == list(CALIBRATION.ids)  # stopped by the 0.3 s silence
        failed: list[DriverError] = []
        for _ in range(20):  # a loaded machine may add timeouts of its own
            try:
                q = driver.read_state().q_rad
                break
            except DriverError as exc:  # nothing else: no struct.error, no IndexError
                failed.append(exc)
        if fault.startswith("short"):
            assert any(isinstance(e, BadReplyError) and re.search(
                "servo 1 answered 9 bytes where 10", str(e)) for e in failed), failed  # fmt: skip
        with arm.bus.lock:
            np.testing.assert_allclose(q, arm.physics.state.q, atol=0.02)  # whole again


def test_the_buttons_board_reports_the_cap_within_its_travel() -> None:
    """MuJoCo's soft stop lets a dragged cap rise past it; the board, as a real one behind
    its stop, reads it at rest (it once reported -3 mm, and the driver refused the whole
    bus's reading as not a reading)."""
    task = TaskSettings()
    physics = MujocoServos(CALIBRATION, RobotSettings().load(), task)
    travel = scene_layout(task).button_travel_m
    sim = physics.sim
    cap = sim.model.jnt_qposadr[sim.model.joint("button").id]
    for qpos_m, sensed_m in ((0.003, 0.0), (-0.005, 0.005), (-0.03, travel)):
        sim.data.qpos[cap] = qpos_m  # above its stop, pressed, pressed past its travel
        mujoco.mj_forward(sim.model, sim.data)
        physics.state = sim.read()
        assert physics.button_travel_m() == pytest.approx(sensed_m, abs=1e-9)
        low, high = BUTTON_RANGE_UM
        assert low <= round(physics.button_travel_m() * 1e6) <= high  # the driver's range


# ---- the tools: scan, jog, calibrate -----------------------------------------------------
def test_scan_finds_every_servo_and_the_button(arm: EmulatedArm) -> None:
    devices = scan(str(arm.bus.link))
    assert [d.servo_id for d in devices] == [1, 2, 3, 4, 5, 6, 100]
    assert {d.model for d in devices} == {XM430_W350, BUTTON_MODEL} and devices[0].firmware == 46


def test_jog_moves_one_joint_by_what_was_asked_and_holds_the_others(arm: EmulatedArm) -> None:
    driver = DynamixelDriver(str(arm.bus.link), CALIBRATION)
    settings = ArmSettings(soft_start_s=0.2)
    before = arm.physics.state.q.copy()
    moved = jog(driver, RobotSettings().load(), settings, 3, -0.1, 0.3, lambda _: None)
    assert moved == pytest.approx(-0.1, abs=0.01)
    after = arm.physics.state.q
    assert after[3] - before[3] == pytest.approx(-0.1, abs=0.01)
    np.testing.assert_allclose(np.delete(after, 3), np.delete(before, 3), atol=0.01)


def test_the_guided_calibration_finds_directions_offsets_and_limits(arm: EmulatedArm) -> None:
    """The person moves the unpowered emulated arm by hand as each prompt asks."""
    robot = RobotSettings().load()
    q = arm.physics.state.q.copy()
    lower = robot.q_min + 0.2
    upper = robot.q_max - 0.3

    def person(prompt: str) -> None:
        joint = next((j for j, n in enumerate(robot.joint_names) if f" {n} " in prompt), None)
        if "positive direction" in prompt and joint is not None:
            q[joint] += 0.2
        elif "reference posture" in prompt:
            q[:] = 0.0
        elif "lower end" in prompt and joint is not None:
            q[joint] = lower[joint]
        elif "upper end" in prompt and joint is not None:
            q[joint] = upper[joint]
        arm.move_by_hand(q)

    base = Calibration(gear_ratios=CALIBRATION.gear_ratios)
    found = guided_calibration(str(arm.bus.link), base, robot, True, person, lambda _: None)
    assert found.directions == CALIBRATION.directions
    np.testing.assert_allclose(found.offsets_rad, CALIBRATION.offsets_rad, atol=2 / 651.9)
    np.testing.assert_allclose(found.q_min_rad or (), lower, atol=0.01)
    np.testing.assert_allclose(found.q_max_rad or (), upper, atol=0.01)
    with arm.bus.lock:
        assert not any(s.torque_on for s in arm.chain.motors.values())  # never powered


# ---- the node, driven cycle by cycle --------------------------------------------------------
HEADER = Header(stamp_ns=1, seq=0, source="test")


@dataclass
class _Publisher:
    bus: QueueBus
    kind: type[Message]

    def stamp(self) -> Header:
        return Header(stamp_ns=time.time_ns(), seq=0, source="robot")

    def send(self, message: Message) -> Message:
        self.bus.published.append(message)
        return message


@dataclass
class QueueBus:
    """The node's bus in-process: messages in through ``send``, out in ``published``."""

    inbox: list[Message] = field(default_factory=list)
    published: list[Message] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)
    health: list[tuple[str, str]] = field(default_factory=list)

    def publisher(self, kind: type[Message]) -> _Publisher:
        return _Publisher(self, kind)

    def subscribe(self, *kinds: type[Message]) -> None: ...
    def expect(self, kind: type[Message], *sources: str) -> None: ...

    def key(self, kind: type[Message]) -> str:
        return kind.__name__

    def receive(self, timeout_s: float | None) -> Message | None:
        return self.inbox.pop(0) if self.inbox else None

    def receive_all(self, timeout_s: float) -> list[Message]:
        taken, self.inbox = self.inbox, []
        return taken

    def reject(self, key: str, reason: str) -> None:
        self.rejected.append(reason)

    def report_health(self, state: str = "ok", detail: str = "", force: bool = False) -> None:
        self.health.append((state, detail))

    def alive_peers(self) -> set[str]:
        return {"controller"}

    def send(self, message: Message) -> None:
        self.inbox.append(message)

    def states(self) -> list[RobotState]:
        return [m for m in self.published if isinstance(m, RobotState)]


@dataclass
class Rig:
    node: RobotNode
    bus: QueueBus
    arm: EmulatedArm
    speeds: list[np.ndarray] = field(default_factory=list)  # true joint speeds per cycle
    gaps: list[np.ndarray] = field(default_factory=list)  # |q_ref applied - q| per cycle

    def run(self, seconds: float, each: Callable[[Rig], None] | None = None) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.node.cycle()
            if each is not None:
                each(self)
            self.speeds.append(self.arm.joint_speeds())
            state = self.bus.states()[-1] if self.bus.states() else None
            if state is not None and state.q_ref_applied_rad is not None:
                self.gaps.append(np.abs(np.subtract(state.q_ref_applied_rad, state.q_rad)))
            time.sleep(0.01)

    def run_until(self, done: Callable[[Rig], bool], timeout_s: float,
                  each: Callable[[Rig], None] | None = None) -> None:  # fmt: skip
        """Cycles until ``done`` (checked every 0.1 s), at most ``timeout_s``: a loaded
        machine may take longer than a quiet one to get there."""
        deadline = time.monotonic() + timeout_s
        while not done(self):
            if time.monotonic() > deadline:
                health = self.bus.health[-1] if self.bus.health else None
                raise AssertionError(f"not done after {timeout_s} s; Health {health}")
            self.run(0.1, each)

    def fastest(self, since: int = 0, joints: list[int] | None = None) -> float:
        """The fastest any of ``joints`` (default all) moved since cycle ``since`` [rad/s]."""
        rows = np.array(self.speeds[since:])
        return float(rows[:, joints if joints is not None else slice(None)].max())

    @property
    def last_health(self) -> tuple[str, str]:
        return self.bus.health[-1]


@pytest.fixture()
def rig(arm: EmulatedArm, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Rig]:
    path = tmp_path / "arm.json"
    save_calibration(CALIBRATION, path)
    settings = ArmSettings(soft_start_s=0.3, homing_speed_rad_s=0.6)
    driver = DynamixelDriver(str(arm.bus.link), load_calibration(path))
    bus = QueueBus()
    node = RobotNode(settings, TaskSettings(), RobotSettings(), bus, driver)  # type: ignore[arg-type]
    yield Rig(node, bus, arm)
    if node.connected:
        node.driver.disconnect()


def _goal(episode: int, q_start: tuple[float, ...] = (0.1, 0.9, 0.0, 1.5, 0.1, 0.3)) -> TaskGoal:
    return TaskGoal(header=Header(stamp_ns=1, seq=episode, source="controller"),
                    episode=episode, seed=episode, start_m=(0.3, 0, 0), goal_m=(0.45, 0, 0),
                    q_start_rad=q_start)  # fmt: skip


def _answer(rig: Rig, offset: np.ndarray) -> None:
    """A controller: each new state answered with a reference ``offset`` from home."""
    state = rig.bus.states()[-1]
    if state.episode == 0 or rig.node.law.homing is not None:
        return
    q_ref = np.array(_goal(1).q_start_rad) + offset
    gravity = rig.node.arm.inverse_dynamics(q_ref, np.zeros(6), np.zeros(6))
    rig.bus.send(JointCommand(
        header=Header(stamp_ns=time.time_ns(), seq=0, source="controller"),
        episode=state.episode, state_stamp_ns=state.header.stamp_ns, q_ref_rad=tuple(q_ref),
        dq_ref_rad_s=(0.0,) * 6, tau_ff_nm=tuple(gravity),
        kp_nm_per_rad=(400.0, 400, 200, 200, 50, 50), kd_nms_per_rad=(30.0, 30, 12, 12, 1.5, 1.5),
    ))  # fmt: skip


def _started(rig: Rig) -> None:
    """Connected, soft-started, homed to episode 1's start and following commands."""
    rig.run_until(lambda r: r.node.connected and bool(r.bus.health)
                  and r.last_health[0] == "holding", 20)  # fmt: skip
    rig.bus.send(_goal(1))
    rig.run_until(lambda r: r.node.law.episode == 1 and r.last_health[0] == "ok", 20,
                  lambda r: _answer(r, np.zeros(6)))  # fmt: skip


def test_the_node_homes_follows_commands_and_holds_when_they_stop(rig: Rig) -> None:
    _started(rig)
    target = np.array([0.05, -0.05, 0.05, 0.05, 0.0, 0.0])
    rig.run(1.5, lambda r: _answer(r, target))
    state = rig.bus.states()[-1]
    np.testing.assert_allclose(state.q_rad, np.array(_goal(1).q_start_rad) + target, atol=0.01)
    assert 1.5 < state.t_s < 5.5 and not state.holding  # robot time: from the episode start
    rig.run(0.5)  # the controller went quiet
    assert rig.bus.states()[-1].holding and rig.last_health[0] == "holding"
    assert rig.fastest(len(rig.speeds) - 20) < 0.02


def test_the_emergency_stop_holds_within_one_period_and_refuses_commands(rig: Rig) -> None:
    _started(rig)
    rig.run(0.2, lambda r: _answer(r, np.array([0.3, 0, 0, 0, 0, 0])))  # moving away
    assert rig.fastest(len(rig.speeds) - 5) > 0.1
    rig.bus.send(EmergencyStop(header=Header(stamp_ns=1, seq=0, source="operator"), engaged=True))
    rig.node.cycle()  # one period
    assert rig.last_health[0] == "stopped"
    assert rig.node.law.held is not None and rig.node.law.command is None
    cycles = len(rig.speeds)
    rig.run(1.0, lambda r: _answer(r, np.array([0.3, 0, 0, 0, 0, 0])))
    stopped_at = next(i for i, s in enumerate(rig.speeds[cycles:]) if s.max() < 0.02)
    assert stopped_at * 0.011 < 0.5, rig.speeds[cycles:]  # at rest within half a second
    assert any("emergency stop" in r for r in rig.bus.rejected)
    assert rig.node.law.held is not None
    np.testing.assert_array_equal(rig.node.law.held.kp, rig.node.settings.stop_kp_nm_per_rad)
    rig.bus.send(EmergencyStop(header=Header(stamp_ns=2, seq=1, source="operator"), engaged=False))
    rig.run(0.3)
    assert rig.last_health[0] == "holding"  # released: it holds until commands resume
    held = rig.node.law.held  # with the ordinary hold's gains, not the stop's
    assert held is not None
    np.testing.assert_array_equal(held.kp, rig.node.settings.hold_kp_nm_per_rad)


def test_a_torque_off_stop_stays_off_across_a_lost_bus_and_reconnection(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """STOP_ACTION=torque_off: a cable wiggle after the stop (the bus lost, then back) left
    the torque on again with the hold law, while Health said stopped; and a limp arm,
    written nothing, was taken for a stalled one and re-armed every cycle."""
    _started(rig)
    rig.node.settings = rig.node.settings.model_copy(update={"stop_action": "torque_off"})
    rig.bus.send(EmergencyStop(header=Header(stamp_ns=1, seq=0, source="operator"), engaged=True))
    rig.node.cycle()
    servos = rig.arm.chain.servos
    assert rig.node.link.limp and all(servos[i].table[TORQUE_ENABLE] == 0 for i in range(1, 7))
    rearms = []
    monkeypatch.setattr(rig.node.driver, "rearm", lambda: rearms.append(1) or [])
    rig.run(0.3)
    assert not rearms  # nothing is written: no stall to suspect
    read, failures = rig.node.driver.read_state, [DriverError("sync read failed")] * 3

    def wiggle() -> JointState:
        if failures:
            raise failures.pop()
        return read()

    monkeypatch.setattr(rig.node.driver, "read_state", wiggle)
    rig.run_until(lambda r: not failures and r.node.connected and r.node.joint is not None, 10)
    assert rig.node.link.limp and all(servos[i].table[TORQUE_ENABLE] == 0 for i in range(1, 7))
    assert rig.last_health[0] == "stopped"


def test_after_a_stall_longer_than_the_watchdog_the_servos_obey_again(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    """The watchdog stopped the servos while this process was silent; they refuse goals
    (silently, in a sync write) until re-armed: the node re-arms them and goes on."""
    _started(rig)
    time.sleep(0.3)  # a stall: three watchdog periods without a packet
    with rig.arm.bus.lock:
        assert all(s.watchdog_expired for s in rig.arm.chain.motors.values())
    target = np.array([0.05, -0.05, 0.05, 0.05, 0.0, 0.0])
    rig.run(1.5, lambda r: _answer(r, target))
    state = rig.bus.states()[-1]
    np.testing.assert_allclose(state.q_rad, np.array(_goal(1).q_start_rad) + target, atol=0.01)
    assert "the drives [1, 2, 3, 4, 5, 6] had stopped themselves" in caplog.text


def _stop_by_their_clock(arm: EmulatedArm) -> None:
    """The servos' watchdog runs out by their own clock, not this host's (a starved
    emulator, a USB adapter holding packets back): they stop at the next packet."""
    with arm.bus.lock:
        for servo in arm.chain.motors.values():
            servo.watchdog_deadline_s = arm.chain.now_s


def _holding(rig: Rig) -> None:
    rig.run_until(lambda r: r.node.connected and bool(r.bus.health)
                  and r.last_health[0] == "holding", 20)  # fmt: skip


def test_servos_stopped_by_their_own_clock_are_rearmed_after_a_failed_cycle(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    """Seen beside two CPU hogs (the compose real profile): two failed bus cycles, no
    silence by the host's clock, the servos stopped by their watchdog and refusing goals,
    the move to the start never made and the episode refused for good. After a failed
    cycle the node now asks the servos, re-arms those stopped, and the move goes on."""
    _holding(rig)
    _stop_by_their_clock(rig.arm)
    inject(rig.arm, "corrupt 1")  # one failed cycle, far shorter than the watchdog
    rig.bus.send(_goal(1))
    rig.run_until(lambda r: r.node.law.episode == 1, 20, lambda r: r.bus.send(_goal(1)))
    assert "the drives [1, 2, 3, 4, 5, 6] had stopped themselves" in caplog.text
    assert rig.node.law.homing_failure is None


def test_servos_stopped_by_their_own_clock_while_following_are_found_and_rearmed(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    """No failed cycle and no stall by this host's clock: the servos' watchdog ran out
    (a packet held back) while they followed commands; they refuse goals silently and the
    arm rests where it was, Health 'ok'. A reference not followed for a second makes the
    node ask them: re-armed, the arm follows again."""
    _started(rig)
    _stop_by_their_clock(rig.arm)
    target = np.array([0.12, 0, 0, 0, 0, 0])
    start = _true_q(rig)[0]
    rig.run_until(lambda r: _true_q(r)[0] - start > 0.08, 20, lambda r: _answer(r, target))
    assert "had stopped themselves" in caplog.text


def test_a_start_missed_for_stopped_servos_is_tried_again_not_refused(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    """Servos stopped by their own clock with no failed cycle to tell: the move to the
    start gives up. Before it refuses the episode the node asks the servos, finds them
    stopped and re-arms them: no refusal goes out (the controller would end the episode),
    and the episode, announced again, is homed and begins."""
    rig.node.law.settings = rig.node.law.settings.model_copy(update={"homing_timeout_s": 0.3})
    _holding(rig)
    _stop_by_their_clock(rig.arm)
    rig.bus.send(_goal(1))
    rig.run_until(lambda r: r.node.law.episode == 1, 20, lambda r: r.bus.send(_goal(1)))
    assert "episode 1: tried again when announced (the drives had stopped)" in caplog.text
    assert not [m for m in rig.bus.published if isinstance(m, GoalRefused)]


def test_a_start_missed_by_servos_that_stop_on_every_try_is_refused_after_two(
    rig: Rig, caplog: pytest.LogCaptureFixture
) -> None:
    """Servos that stop on their own clock at every try would have the episode tried
    again for good (the session held on it): after two tries it is refused all the same."""
    rig.node.law.settings = rig.node.law.settings.model_copy(update={"homing_timeout_s": 0.3})
    _holding(rig)
    rig.bus.send(_goal(1))

    def stopping(r: Rig) -> None:
        _stop_by_their_clock(r.arm)
        r.bus.send(_goal(1))

    rig.run_until(lambda r: any(isinstance(m, GoalRefused) for m in r.bus.published), 30,
                  stopping)  # fmt: skip
    assert caplog.text.count("episode 1: tried again when announced") == START_RETRIES


def test_a_start_posture_never_reached_refuses_the_episode_and_holds(rig: Rig) -> None:
    """Blocked (here: a tolerance no arm meets), the move gives up and the arm holds."""
    rig.node.law.settings = rig.node.law.settings.model_copy(
        update={"homing_tolerance_rad": 1e-6, "homing_timeout_s": 0.3}
    )
    rig.run(0.5)
    rig.bus.send(_goal(1))
    rig.run(4.0, lambda r: r.bus.send(_goal(1)))  # the controller announces it again
    assert rig.node.law.episode == 0 and rig.node.law.homing is None
    assert sum("start posture not reached" in r for r in rig.bus.rejected) > 1
    refusals = [m for m in rig.bus.published if isinstance(m, GoalRefused)]
    assert refusals and {m.episode for m in refusals} == {1}  # the controller ends it
    assert refusals[0].reason.startswith("episode 1: the start posture not reached")
    state, detail = rig.last_health
    assert state == "holding" and "episode 1: the start posture not reached" in detail
    assert rig.fastest(len(rig.speeds) - 20) < 0.02


def test_a_bus_error_while_the_drives_are_asked_before_a_refusal_is_a_failed_cycle(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before it refuses a start not reached the node asks the drives; a bus error then
    is one failed cycle like any other (the service lives on), and the refusal goes out
    at the next announcement."""
    rig.node.law.settings = rig.node.law.settings.model_copy(
        update={"homing_tolerance_rad": 1e-6, "homing_timeout_s": 0.3}
    )
    rearm, failures = rig.node.driver.rearm, []

    def rearm_failing_once() -> list[int]:
        if not failures:
            failures.append(1)
            raise DriverError("no answer from servo 3")
        return rearm()

    monkeypatch.setattr(rig.node.driver, "rearm", rearm_failing_once)
    rig.run(0.5)
    rig.bus.send(_goal(1))
    rig.run(4.0, lambda r: r.bus.send(_goal(1)))
    assert failures and rig.node.connected
    refusals = [m for m in rig.bus.published if isinstance(m, GoalRefused)]
    assert refusals and refusals[0].episode == 1


@pytest.mark.parametrize(
    ("fault", "health", "recovery"),
    [("corrupt 2", "ok", None), ("missing 3", "degraded", "present 3"),
     ("silent", "degraded", "talk"), ("unplug", "degraded", "replug"),
     ("overload 6", "stopped", None)],
)  # fmt: skip
def test_every_fault_ends_in_a_hold_or_a_stop_without_a_jump(
    rig: Rig, fault: str, health: str, recovery: str | None
) -> None:
    """The reference never leaves the arm (|q_ref - q| as in normal running) and nothing
    moves but what gravity does to a servo its own firmware or watchdog stopped."""
    _started(rig)
    rig.run(0.3, lambda r: _answer(r, np.zeros(6)))
    before, steady = len(rig.speeds), max(float(g.max()) for g in rig.gaps[-20:])
    inject(rig.arm, fault)
    rig.run(1.5, lambda r: _answer(r, np.zeros(6)))
    assert rig.last_health[0] == health, rig.bus.health[-3:]
    others = [0, 1, 2, 3, 4] if fault.startswith("overload") else None  # servo 6 is cut
    gaps = np.array(rig.gaps[before:])[:, others if others else slice(None)]
    assert gaps.max() < steady + 0.01, (gaps.max(), steady)  # held where it was: no jump
    # the others hold (the wrist's fall and its catch after the reboot shake them); or the
    # watchdog's stop holds without gravity compensation: a slow settle
    fastest = rig.fastest(before, others)
    assert fastest < 0.3, (fastest, rig.bus.health[-3:])
    if recovery is not None:  # the bus comes back: the arm holds where it is
        inject(rig.arm, recovery)
        rig.run(2.0)
        assert rig.last_health[0] == "holding", rig.bus.health[-3:]
        for _ in range(20):  # settled: on a loaded machine (fewer cycles a second) later
            if rig.fastest(len(rig.speeds) - 50) < 0.05:
                break
            rig.run(0.1)
        assert rig.fastest(len(rig.speeds) - 50) < 0.05


def test_a_late_answer_after_a_stall_is_a_counted_bus_error_and_the_arm_goes_on(
    rig: Rig, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After a stall the node re-arms the servos one read at a time; an answer that comes
    late costs that read a retry (before: a failed re-arm, and the late answer met by the
    next cycle's sync read as a failed cycle), and the arm follows commands again (the
    service lived on)."""
    _started(rig)
    target = np.array([0.05, -0.05, 0.05, 0.05, 0.0, 0.0])
    rearm = rig.node.driver.rearm

    def rearm_answered_late() -> list[int]:
        if not rearmed:
            rearmed.append(True)
            inject(rig.arm, "late 1")  # servo 1's answer to the re-arm's first read
        return rearm()

    rearmed: list[bool] = []
    monkeypatch.setattr(rig.node.driver, "rearm", rearm_answered_late)
    time.sleep(0.3)  # a stall: the watchdog stops the servos, the node re-arms them
    rig.run(1.5, lambda r: _answer(r, target))
    assert rearmed and rig.arm.chain.faults.late_responses == 0  # the late answer came
    assert "had stopped themselves" in caplog.text
    for _ in range(30):  # on a loaded machine the emulator's own timeouts come on top
        if (
            np.abs(rig.bus.states()[-1].q_rad - np.array(_goal(1).q_start_rad) - target).max()
            < 0.02
        ):
            break
        rig.run(0.2, lambda r: _answer(r, target))
    np.testing.assert_allclose(rig.bus.states()[-1].q_rad,
                               np.array(_goal(1).q_start_rad) + target, atol=0.02)  # fmt: skip
    assert rig.last_health[0] == "ok", rig.last_health


def _true_q(rig: Rig) -> np.ndarray:
    with rig.arm.bus.lock:
        return np.array(rig.arm.physics.state.q)


def test_an_overloaded_servo_is_rebooted_and_holds_where_its_joint_is(rig: Rig) -> None:
    """Servo 6 (wrist pitch, loaded by the hand's weight) cuts its torque mid-motion: the
    arm stops, the servo is rebooted at once and, back after its boot, holds the joint
    where it is then (not pulled back up); the other joints hold meanwhile. A second
    overload beyond max_restarts leaves it off, said in Health."""
    rig.arm.chain.boot_s = 0.1
    rig.node.law.recovery.max_restarts = 1
    _started(rig)
    rig.run(0.3, lambda r: _answer(r, np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.2])))  # moving
    q0 = _true_q(rig)
    inject(rig.arm, "overload 6")
    rig.run(1.5)
    state, detail = rig.last_health
    assert state == "stopped" and "joint 6's drive back after a restart" in detail, detail
    q1 = _true_q(rig)
    fall = abs(q1[5] - q0[5])
    print(f"wrist pitch fell {fall:.3f} rad during a 0.1 s reboot")
    assert fall < 0.6, fall  # measured 0.05-0.2 rad at a 0.1 s boot (without: to the limit)
    assert np.abs(q1[:5] - q0[:5]).max() < 0.02  # the others held
    rig.run(1.0)
    assert np.abs(_true_q(rig) - q1).max() < 0.01  # back: held there, no jump
    assert rig.fastest(len(rig.speeds) - 50) < 0.05
    inject(rig.arm, "overload 6")
    rig.run(0.5)
    assert "left off after 1 restarts: support the arm" in rig.last_health[1]


def _lose_reboots(rig: Rig, monkeypatch: pytest.MonkeyPatch, count: int) -> None:
    """The next ``count`` REBOOT packets never reach their servo (noise on the bus)."""
    packet = rig.node.driver._packet
    sent = packet.reboot
    lost = [count]

    def reboot(port: object, servo_id: int) -> tuple[int, int]:
        if lost[0] > 0:
            lost[0] -= 1
            return 0, 0
        return sent(port, servo_id)  # type: ignore[no-any-return]

    monkeypatch.setattr(packet, "reboot", reboot)


def test_a_reboot_that_never_reached_its_servo_is_sent_again(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A lost REBOOT left the servo answering with its overload latched: the restore's
    torque-on was refused cycle after cycle, the bus counted lost, the reconnect refused
    the latched error, and the joint fell as if never restarted (0.70 rad here). The
    pings now see the error still latched and send the REBOOT again."""
    rig.arm.chain.boot_s = 0.05
    _started(rig)
    rig.run(0.3, lambda r: _answer(r, np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.2])))  # moving
    q0 = _true_q(rig)
    _lose_reboots(rig, monkeypatch, 1)
    inject(rig.arm, "overload 6")
    rig.run(1.5)
    state, detail = rig.last_health
    assert state == "stopped" and "joint 6's drive back after a restart" in detail, detail
    assert rig.node.connected and rig.node.link.bus_errors == 0
    fall = abs(_true_q(rig)[5] - q0[5])
    print(f"wrist pitch fell {fall:.3f} rad with its first REBOOT lost")
    assert fall < 0.4, fall  # measured 0.15 rad (a 0.05 s boot, one lost REBOOT)


def test_a_drive_a_restart_does_not_clear_is_left_off_and_said(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every REBOOT lost (or a fault that outlives it): after a bounded number of REBOOTs
    the drive is said left off, the bus stays connected and the other joints hold."""
    _started(rig)
    rig.run(0.3, lambda r: _answer(r, np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.2])))  # moving
    q0 = _true_q(rig)
    _lose_reboots(rig, monkeypatch, 100)
    inject(rig.arm, "overload 6")
    rig.run_until(lambda r: "still faulted" in r.last_health[1], 10)
    state, detail = rig.last_health
    assert state == "stopped" and "support the arm at this joint" in detail, detail
    rig.run(0.5)
    assert rig.node.connected and rig.node.link.bus_errors == 0
    assert np.abs(_true_q(rig)[:5] - q0[:5]).max() < 0.02  # the others held


def test_a_servo_bus_pulled_out_fails_as_a_lost_port_and_reconnects_once_plugged_back(
    tmp_path: Path,
) -> None:
    """The adapter pulled out: every request fails as a DriverError (the SDK's flush raised
    termios.error, which crashed the service), and a connect that fails closes the port,
    so the same adapter plugged back is opened afresh (the SDK's port stayed "in use")."""
    link = tmp_path / "ttyROBOT"
    driver = DynamixelDriver(str(link), CALIBRATION)
    with emulated_arm(link, CALIBRATION) as first:
        driver.connect()
        first.bus.pull_out()
        for _ in range(3):
            with pytest.raises(DriverError):
                driver.read_state()
        with pytest.raises(DriverError):
            driver.connect()
    with emulated_arm(link, CALIBRATION):  # plugged back: a new device at the same path
        driver.connect()
        assert driver.read_state().q_rad.shape == (6,)
        driver.disconnect()


def test_a_connect_survives_a_garbled_answer(arm: EmulatedArm) -> None:
    """A connect is a dozen requests; a garbled answer to one of them costs that request
    a retry, not the whole connect (on a loaded PC, the node's retries of whole connects
    ran into the next garbled answer)."""
    driver = DynamixelDriver(str(arm.bus.link), CALIBRATION)
    inject(arm, "corrupt 2")  # the first two answers (to the first ping and its retry)
    try:
        driver.connect()
        assert arm.chain.faults.corrupt_responses == 0
        with arm.bus.lock:
            assert all(arm.chain.servos[i].torque_on for i in CALIBRATION.ids)
    finally:
        driver.disconnect()


def test_an_overheated_servo_is_left_off_and_said_while_the_others_hold(rig: Rig) -> None:
    """Servo 6 overheats mid-motion (its torque cut, a fault a reboot does not clear): the
    arm stops, the servo is never rebooted and stays off, Health says to support the arm,
    and the other joints hold where they were."""
    _started(rig)
    rig.run(0.3, lambda r: _answer(r, np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.2])))  # moving
    q0 = _true_q(rig)
    inject(rig.arm, "overheat 6")
    rig.run_until(lambda r: "left off" in r.last_health[1], 10)
    rig.run(0.5)
    state, detail = rig.last_health
    assert state == "stopped" and "overheating: left off" in detail, detail
    assert "support the arm" in detail, detail
    assert rig.node.law.recovery.restarts[5] == 0  # never rebooted
    with rig.arm.bus.lock:
        assert rig.arm.chain.servos[6].booting_until_s is None
        assert rig.arm.chain.servos[6].table[TORQUE_ENABLE] == 0  # still off
    assert np.abs(_true_q(rig)[:5] - q0[:5]).max() < 0.02  # the others held


def test_a_controller_starting_where_the_arm_rests_after_homing_meets_no_cap(rig: Rig) -> None:
    """Homing ends once the arm rests near its start (within the homing tolerance); the
    controller's reach begins where the arm is measured. The hold between them is there
    too: the first command (the measured posture) is no jump for the arm's rate cap (the
    hold at the exact start posture made command #1 of every episode a clamp)."""
    rig.node.law.settings = rig.node.law.settings.model_copy(
        update={"homing_tolerance_rad": 0.08}
    )  # the arm may still lag the move's end when the episode begins

    def answer_measured(r: Rig) -> None:
        state = r.bus.states()[-1]
        if state.episode == 0 or r.node.law.homing is not None:
            return
        gravity = r.node.arm.inverse_dynamics(np.array(state.q_rad), np.zeros(6), np.zeros(6))
        r.bus.send(JointCommand(
            header=Header(stamp_ns=time.time_ns(), seq=0, source="controller"),
            episode=state.episode, state_stamp_ns=state.header.stamp_ns, q_ref_rad=state.q_rad,
            dq_ref_rad_s=(0.0,) * 6, tau_ff_nm=tuple(gravity),
            kp_nm_per_rad=(400.0, 400, 200, 200, 50, 50),
            kd_nms_per_rad=(30.0, 30, 12, 12, 1.5, 1.5),
        ))  # fmt: skip

    rig.run(0.5)
    starts = ((0.1, 0.9, 0.0, 1.5, 0.1, 0.3), (-0.4, 0.5, 0.3, 1.0, 0.0, 0.0))
    for episode, start in enumerate(starts, 1):
        rig.bus.send(_goal(episode, start))
        rig.run(4.0, answer_measured)
        assert rig.node.law.episode == episode, rig.bus.rejected
    assert rig.node.law.freshness.clamped == 0


# ---- the law alone, in robot time -----------------------------------------------------------
def _moving_law(speed_share: float) -> tuple[ArmLaw, Callable[[float], np.ndarray]]:
    """An arm law holding at a start posture at robot time 0, and a reference moving every
    joint from there at ``speed_share`` of its capped speed (as a function of robot time)."""
    settings = ArmSettings()
    robot = RobotSettings().load()
    limits = arm_limits(robot, (robot.q_min, robot.q_max), settings)
    law = ArmLaw(settings, limits, scene_layout(TaskSettings()), ArmModel(robot), 0.01, 0.0)
    q0 = np.array(_goal(1).q_start_rad)
    law.law(JointState(q0, np.zeros(6), np.zeros(6)), 0.0, 1.0, lambda: "quiet")  # a hold
    return law, lambda t: q0 + speed_share * limits.dq_max * t


def _command(law: ArmLaw, q_ref: np.ndarray, stamp: int) -> str | None:
    gains = np.array(law.settings.hold_kp_nm_per_rad), np.array(law.settings.hold_kd_nms_per_rad)
    joint = JointState(q_ref, np.zeros(6), np.zeros(6))
    return law.take_command(CoreCommand(q_ref, np.zeros(6), np.zeros(6), *gains), stamp, joint,
                            stamp * 0.01)  # fmt: skip


def test_commands_taken_in_one_cycle_are_capped_from_each_other() -> None:
    """On a loaded machine the commands answering two consecutive states can reach the
    robot in one cycle. The rate cap allows the robot time between the states each one
    answers, so the second must move from the first, not from the last reference written
    to the drives (that made a controller at 0.75 of the cap speed meet the cap: a clamp
    in a CI run; the sim always moved from the reference in force)."""
    law, reference = _moving_law(0.75)
    for stamp in (1, 2, 3):
        law.freshness.published(stamp, stamp * 0.01)  # states 10 ms apart
    assert _command(law, reference(0.01), 1) is None
    law.law(JointState(reference(0.01), np.zeros(6), np.zeros(6)), 0.015, 1.0, lambda: "")
    assert _command(law, reference(0.02), 2) is None  # these two in one cycle
    assert _command(law, reference(0.03), 3) is None
    assert law.freshness.clamped == 0
    np.testing.assert_array_equal(law.last_q_ref, reference(0.03))


def test_commands_taken_together_move_the_reference_no_faster_than_the_cap() -> None:
    law, reference = _moving_law(1.5)
    for stamp in (1, 2):
        law.freshness.published(stamp, stamp * 0.01)
    _command(law, reference(0.01), 1)
    _command(law, reference(0.02), 2)  # both before the next write
    assert law.freshness.clamped == 2 and law.command is not None
    moved = np.abs(law.command.q_ref - reference(0.0))
    assert np.all(moved <= law.limits.dq_max * 0.02 + 1e-12)


def _law_at_rest() -> tuple[ArmLaw, np.ndarray]:
    settings = ArmSettings()
    robot = RobotSettings().load()
    limits = arm_limits(robot, (robot.q_min, robot.q_max), settings)
    law = ArmLaw(settings, limits, scene_layout(TaskSettings()), ArmModel(robot), 0.01, 0.0)
    return law, np.array(TaskSettings().home_q_rad)


def test_a_goal_never_reachable_is_refused_to_the_controller_one_of_the_arms_state_waits() -> None:
    """A start beyond the limits can never begin: refused, for the controller to end it.
    A stopped arm refuses every goal until released: that episode waits (no refusal
    goes out, or a session would burn through its trials while the arm is stopped)."""
    law, q = _law_at_rest()
    rest = JointState(q, np.zeros(6), np.zeros(6))
    beyond = q + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 6.0])
    assert law.take_goal(Start(1, beyond), (0.45, 0, 0), rest, 0.0) is None
    assert [(e, "outside the joint limits" in why) for e, why in law.refused] == [(1, True)]
    law.refused.clear()
    law.stop_latch.take(True, "operator", "T1")
    assert law.take_goal(Start(2, q), (0.45, 0, 0), rest, 0.0) is not None
    assert law.refused == [] and law.homing is None


def test_homing_an_arm_held_back_keeps_its_reference_near_the_arm() -> None:
    """The person (or the table) holds the arm during the move to the start: the homing
    reference ran on to the start (0.8 rad away), so the arm let go lunged after it at its
    torque limit. It stays within a command's cap of the arm, as the controller's do."""
    law, q = _law_at_rest()
    held = JointState(q, np.zeros(6), np.zeros(6))
    start = q + np.array([0.0, 0.8, 0.0, 0.0, 0.0, 0.0])
    assert law.take_goal(Start(1, start), (0.45, 0, 0), held, 0.0) is None
    gaps = [float(np.max(np.abs(law.law(held, k * 0.01, 1.0, lambda: "").q_ref - q)))
            for k in range(1, 400)]  # fmt: skip
    assert max(gaps) <= law.settings.max_relative_target_rad + 1e-12
    assert max(gaps) > 0.1  # it does pull towards the start


def test_a_late_cycle_never_jumps_the_homing_move_ahead() -> None:
    """Homing's reference followed wall time: a cycle 0.9 s late (measured beside two CPU
    hogs) found it 0.9 s further on, a goal jump the servos rushed to (overspeed stops at
    homing). On the move's own clock a late cycle counts as 0.1 s at most."""
    law, q = _law_at_rest()
    rest = JointState(q, np.zeros(6), np.zeros(6))
    assert law.take_goal(Start(1, q + np.array([0.4, -0.3, 0.2, -0.4, 0.3, 0.2])), (0.45, 0, 0),
                         rest, 0.0) is None  # fmt: skip
    previous, now, steps = q, 0.0, []
    for late in [0.01] * 20 + [0.9] + [0.01] * 5 + [0.5]:
        now += late
        q_ref = law.law(rest, now, 1.0, lambda: "").q_ref
        steps.append(float(np.max(np.abs(q_ref - previous))))
        previous = q_ref
    assert max(steps) <= law.settings.homing_speed_rad_s * LATE_CYCLE_S + 1e-9, steps


def test_the_soft_start_and_its_damping_ignore_how_late_a_cycle_is() -> None:
    """The stiffness ramps on the soft start's own clock (a late cycle does not jump it to
    full: a sagged arm would be pulled up hard), the damping is whole from the first law."""
    link = DriveLink(DynamixelDriver("/dev/null"), ArmSettings(soft_start_s=1.0))
    link.ramp = SoftStart.begin(1.0, 0.1, link.max_step_s, 0.0)
    shares = [link.soft_start(t) for t in (0.0, 0.01, 0.92, 0.93)]
    np.testing.assert_allclose(shares, [0.1, 0.109, 0.199, 0.208])
    law, q = _law_at_rest()
    drive = law.law(JointState(q, np.zeros(6), np.zeros(6)), 0.0, 0.1, lambda: "")
    np.testing.assert_allclose(drive.kp, np.array(law.settings.hold_kp_nm_per_rad) * 0.1)
    np.testing.assert_allclose(drive.kd, law.settings.hold_kd_nms_per_rad)


def test_after_a_stall_a_hold_holds_where_the_arm_sagged_to() -> None:
    """The drives stopped themselves during the stall (their feed-forward gone, the arm
    sagged): the hold is taken again where the arm is, not pulled back to where it was."""
    law, q = _law_at_rest()
    law.law(JointState(q, np.zeros(6), np.zeros(6)), 0.0, 1.0, lambda: "")  # holding at q
    sagged = JointState(q + np.array([0.0, -0.3, 0.0, -0.2, 0.0, 0.0]), np.zeros(6), np.zeros(6))
    law.after_stall(sagged, 1.0)
    np.testing.assert_allclose(law.law(sagged, 1.01, 1.0, lambda: "").q_ref, sagged.q_rad)


def test_a_driver_that_cannot_hold_from_its_torque_on_is_refused_at_start(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A plug-in written before connect() took the law to hold with would turn its
    torque on with none in force: one line at start, not a traceback mid-run."""

    class Before:
        def connect(self, torque: bool = True) -> bool:
            return False

    class Plugin:
        settings = dict

        def create(self, settings: object) -> Before:
            return Before()

    monkeypatch.setattr("services.robot.node.driver_plugin", lambda name: Plugin())
    with pytest.raises(ConfigurationError, match=r"'lab-arm' has connect\(\) without 'hold'"):
        make_driver(ArmSettings(driver="lab-arm"))


def test_a_restart_that_never_went_out_stops_the_arm_and_is_sent_again() -> None:
    """A bus error on the REBOOT once left the cycle before the stop: the arm never
    stopped, and the joint was left off as if its restart had not cleared the fault."""
    law, q = _law_at_rest()
    overload = DriveFault(5, "servo 6: overload", restartable=True)
    faulted = JointState(q, np.zeros(6), np.zeros(6), faults=(overload,))
    sent: list[int] = []

    def restart(j: int) -> None:
        if not sent:
            sent.append(-1)
            raise DriverError("writing the REBOOT failed")
        sent.append(j)

    assert law.check(faulted, restart)  # the stop, all the same
    assert not law.check(faulted, restart)  # stopped already; the restart sent again
    assert sent == [-1, 5] and 5 not in law.recovery.off
    assert law.recovery.restarts[5] == 1


def test_a_drive_left_off_is_logged_once_not_every_cycle(caplog: pytest.LogCaptureFixture) -> None:
    """A servo left off keeps its alert bit: every read brings its fault again. It was an
    error line per cycle (100 a second); it is said once, and again when its news change."""
    law, q = _law_at_rest()
    law.recovery.max_restarts = 0
    overload = DriveFault(5, "servo 6: overload", restartable=True)
    for _ in range(50):
        law.check(JointState(q, np.zeros(6), np.zeros(6), faults=(overload,)), lambda j: None)
    notes = [r.message for r in caplog.records if "servo 6" in r.message]
    assert notes == ["servo 6: overload again: left off after 0 restarts: support the arm at "
                     "this joint", "arm fault: servo 6: overload: stopping"], notes  # fmt: skip
