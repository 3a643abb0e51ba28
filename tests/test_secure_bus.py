"""Identity from the transport: only the stack's roles reach the bus, and each role may
publish only its own keys (mutual TLS plus the ACL every session enforces).

The sim runs alone (its arm holds still), so any motion is caused by the test's sessions;
a session with the controller's certificate moving the arm shows the test can see motion.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from schemas import Header, JointCommand, RobotState, TaskGoal, decode, encode, key
from services.common.bus import zenoh_config
from services.common.certificates import create_credentials
from services.common.config import BusSettings
from tests.busutil import free_port, start_service, wait_for

pytestmark = pytest.mark.slow
NEAR_HOME = (0.05, 1.05, 0.05, 1.55, 0.05, 0.35)  # 0.05 rad from home: well inside the caps


@pytest.fixture(scope="module")
def credentials(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("lab") / "bus"
    create_credentials(folder)
    return folder


class Watcher:
    """An observer's session listening on the stack's TLS endpoint, collecting RobotStates."""

    def __init__(self, port: int, credentials: Path) -> None:
        settings = BusSettings(listen=[f"tls/127.0.0.1:{port}"], mode="router",
                               credentials=credentials)  # fmt: skip
        self.session = zenoh.open(zenoh_config(settings, "observer"))
        self.states: list[RobotState] = []
        self._sub = self.session.declare_subscriber(key("dammrl", RobotState), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        self.states.append(decode(RobotState, sample.payload.to_bytes()))

    def motion_mm(self, since: int) -> float:
        x = np.array([s.ee_pos_m for s in self.states[since:]])
        return float(np.max(np.linalg.norm(x - x[0], axis=1)) * 1000)


@pytest.fixture()
def secured_sim(credentials: Path) -> Iterator[tuple[Watcher, int]]:
    port = free_port()
    watcher = Watcher(port, credentials)
    sim = start_service("sim", port, DAMMRL_BUS_CREDENTIALS=str(credentials),
                        DAMMRL_BUS_CONNECT=json.dumps([f"tls/127.0.0.1:{port}"]),
                        DAMMRL_LOG_LEVEL="ERROR")  # fmt: skip
    try:
        wait_for(lambda: len(watcher.states) > 30, 60, "the secured sim's states")
        yield watcher, port
    finally:
        sim.terminate()
        sim.wait(10)
        watcher.session.close()  # type: ignore[no-untyped-call]


def _drive(watcher: Watcher, session: zenoh.Session, seconds: float = 1.0) -> float:
    """Answer the newest states with a command toward NEAR_HOME; the motion it caused [mm]."""
    start, seq = len(watcher.states), 0
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        newest = watcher.states[-1]
        header = Header(stamp_ns=time.time_ns(), seq=seq, source="controller")
        command = JointCommand(header=header, episode=0, state_stamp_ns=newest.header.stamp_ns,
                               q_ref_rad=NEAR_HOME, dq_ref_rad_s=(0.0,) * 6, tau_ff_nm=(0.0,) * 6,
                               kp_nm_per_rad=(400.0,) * 6, kd_nms_per_rad=(30.0,) * 6)  # fmt: skip
        session.put(key("dammrl", JointCommand), encode(command))
        seq += 1
        time.sleep(0.005)
    time.sleep(0.2)
    return watcher.motion_mm(start)


def _session(port: int, credentials: Path | None, role: str) -> zenoh.Session:
    scheme = "tls" if credentials is not None else "tcp"
    settings = BusSettings(connect=[f"{scheme}/127.0.0.1:{port}"], credentials=credentials)
    return zenoh.open(zenoh_config(settings, role))


def test_the_controller_role_moves_the_arm(
    secured_sim: tuple[Watcher, int], credentials: Path
) -> None:
    watcher, port = secured_sim
    with _session(port, credentials, "controller") as controller:
        time.sleep(0.5)
        assert _drive(watcher, controller) > 5.0


def test_another_role_cannot_move_the_arm(
    secured_sim: tuple[Watcher, int], credentials: Path
) -> None:
    watcher, port = secured_sim
    for role in ("intent", "policy", "observer", "display", "operator"):
        with _session(port, credentials, role) as session:
            time.sleep(0.5)
            assert _drive(watcher, session) < 0.01, role


def test_a_peer_without_lab_credentials_cannot_join(
    secured_sim: tuple[Watcher, int], tmp_path: Path
) -> None:
    watcher, port = secured_sim
    with pytest.raises(zenoh.ZError):  # plain tcp to a TLS-only endpoint: no link at all
        _client(f"tcp/127.0.0.1:{port}", None)
    foreign = tmp_path / "foreign"
    create_credentials(foreign)  # a CA the stack does not trust, with a 'controller' cert
    with pytest.raises(zenoh.ZError):
        _client(f"tls/127.0.0.1:{port}", foreign)
    start = len(watcher.states)
    time.sleep(0.5)
    assert watcher.motion_mm(start) < 0.01


def _client(endpoint: str, credentials: Path | None) -> None:
    """A client session (which fails to open when it cannot link)."""
    settings = BusSettings(connect=[endpoint], mode="client", credentials=credentials)
    zenoh.open(zenoh_config(settings, "controller")).close()  # type: ignore[no-untyped-call]


def test_only_the_controller_role_can_reset_the_arm(
    secured_sim: tuple[Watcher, int], credentials: Path
) -> None:
    watcher, port = secured_sim
    header = Header(stamp_ns=time.time_ns(), seq=0, source="controller")
    goal = TaskGoal(header=header, episode=1, seed=0, start_m=(0.3, 0.0, -0.1),
                    goal_m=(0.5, 0.0, -0.21),
                    q_start_rad=(0.3, 0.7, 0.2, 1.2, 0.1, 0.2))  # fmt: skip
    episode_of: Callable[[], int] = lambda: watcher.states[-1].episode  # noqa: E731
    with _session(port, credentials, "intent") as intruder:
        time.sleep(0.5)
        intruder.put(key("dammrl", TaskGoal), encode(goal))
        time.sleep(0.3)
        assert episode_of() == 0
    with _session(port, credentials, "controller") as controller:
        time.sleep(0.5)
        controller.put(key("dammrl", TaskGoal), encode(goal))
        wait_for(lambda: episode_of() == 1, 5, "the reset by the controller")


def test_spoofed_messages_from_another_role_leave_the_episode_exactly_as_in_process(
    credentials: Path,
) -> None:
    from dammrl.stack.runner import ReachRunner
    from schemas import EpisodeResult, ModelChoice
    from tests.busutil import Stack

    seed, port = 7_000_500, free_port()
    watcher = Watcher(port, credentials)
    results: list[EpisodeResult] = []
    sub = watcher.session.declare_subscriber(
        key("dammrl", EpisodeResult),
        lambda s: results.append(decode(EpisodeResult, s.payload.to_bytes())),
    )
    stack = Stack(port, DAMMRL_BUS_CREDENTIALS=str(credentials), DAMMRL_BUS_LOCKSTEP="true",
                  DAMMRL_BUS_CONNECT=json.dumps([f"tls/127.0.0.1:{port}"]),
                  DAMMRL_TASK_SEED=str(seed), DAMMRL_TASK_EPISODES="1", DAMMRL_LOG_LEVEL="ERROR",
                  DAMMRL_POLICY_KIND="fixed", DAMMRL_POLICY_HUMAN_MODEL="2",
                  DAMMRL_POLICY_ROBOT_MODEL="1")  # fmt: skip
    header = Header(stamp_ns=1, seq=0, source="controller")
    local = ReachRunner().run(seed, model=(2, 1))
    fake_result = EpisodeResult(header=header, episode=1, **{
        k: v for k, v in local.summary().items() if k not in ("episode",)
    } | {"success": False, "outcome": "hold", "reason": "spoofed"})  # fmt: skip
    fake_choice = ModelChoice(header=header.model_copy(update={"source": "policy"}), episode=1,
                              request=1, human_model=1, robot_model=8, radius_m=0.01,
                              steps_m=(0.1, 0.1, 0.1))  # fmt: skip
    try:
        with _session(port, credentials, "intent") as intruder:
            deadline = time.monotonic() + 120
            while not results and time.monotonic() < deadline:
                newest = watcher.states[-1] if watcher.states else None
                if newest is not None:  # a state from the future, a huge step, a result
                    forged = newest.model_copy(
                        update={"t_s": newest.t_s + 1e6, "ee_pos_m": (0.5, 0.0, -0.2)}
                    )
                    intruder.put(key("dammrl", RobotState), encode(forged))
                intruder.put(key("dammrl", ModelChoice), encode(fake_choice))
                intruder.put(key("dammrl", EpisodeResult), encode(fake_result))
                time.sleep(0.01)
        assert results, "no episode result"
        bus = results[0]
        expected = local.summary()
        assert (bus.outcome, bus.reason, bus.n_steps) == (
            expected["outcome"],
            expected["reason"],
            expected["n_steps"],
        )
        assert bus.t_total_s == pytest.approx(expected["t_total_s"], abs=1e-9)
        assert len(results) == 1  # the spoofed results never arrived
    finally:
        stack.stop()
        sub.undeclare()  # type: ignore[no-untyped-call]
        watcher.session.close()  # type: ignore[no-untyped-call]


# ---- the people's roles: observer, display, operator --------------------------------------
def _every_topic_from(session: zenoh.Session, source: str) -> None:
    """One well-formed message on every topic of the stack, its header naming ``source``
    (the payload's say decides nothing: only the certificate does)."""
    from tests.test_schemas import EXAMPLES

    for example in EXAMPLES:
        header = example.header.model_copy(update={"source": source})
        message = example.model_copy(update={"header": header})
        session.put(key("dammrl", type(message)), encode(message))


def test_each_persons_role_reaches_only_its_own_keys(credentials: Path) -> None:
    """On a real secured bus, a session with the observer's, the display's and the
    operator's certificate each publishes on every key; a recorder's session receives only
    what the role may send: nothing, the comfort rating, the stop and session control."""
    from services.common.security import PUBLISHES

    port = free_port()
    hub = BusSettings(listen=[f"tls/127.0.0.1:{port}"], mode="router", credentials=credentials)
    received: dict[str, set[str]] = {}  # header.source (the sending role) -> topics

    def take(sample: zenoh.Sample) -> None:
        topic = str(sample.key_expr).removeprefix("dammrl/")
        received.setdefault(_source(sample), set()).add(topic)

    with zenoh.open(zenoh_config(hub, "recorder")) as recorder:
        recorder.declare_subscriber("dammrl/**", take)
        for role in ("observer", "display", "operator"):
            with _session(port, credentials, role) as person:
                time.sleep(0.5)
                _every_topic_from(person, role)
                time.sleep(0.5)
    assert received.get("observer", set()) == set()
    assert received["display"] == set(PUBLISHES["display"]) == {"session/comfort"}
    assert received["operator"] == set(PUBLISHES["operator"])
    assert received["operator"] == {"safety/stop", "session/control"}


def _source(sample: zenoh.Sample) -> str:
    """The header's source of a received message (what the sending test put there)."""
    import msgpack

    return str(msgpack.unpackb(sample.payload.to_bytes())["header"]["source"])


def test_only_the_operators_certificate_stops_and_releases_the_arm(
    secured_sim: tuple[Watcher, int], credentials: Path
) -> None:
    """A viewer's or the participant display's session forging the operator's stop and
    release (header and all) changes nothing; the operator's stops the sim, and only the
    operator's release lets it go."""
    from schemas import EmergencyStop, Health

    watcher, port = secured_sim
    health: list[Health] = []
    sub = watcher.session.declare_subscriber(
        key("dammrl", Health, "sim"), lambda s: health.append(decode(Health, s.payload.to_bytes()))
    )
    sessions = {role: _session(port, credentials, role) for role in ("observer", "display",
                                                                       "operator")}  # fmt: skip
    sent = {role: 0 for role in sessions}

    def stop(role: str, engaged: bool) -> None:
        for _ in range(5):  # as `dammrl stop` does: repeated
            header = Header(stamp_ns=time.time_ns(), seq=sent[role], source="operator")
            sent[role] += 1
            message = EmergencyStop(header=header, engaged=engaged, reason=f"by {role}")
            sessions[role].put(key("dammrl", EmergencyStop), encode(message))
            time.sleep(0.02)

    def state_after(seconds: float = 1.5) -> str:
        health.clear()
        time.sleep(seconds)  # the sim reports a change at once, and every second
        assert health, "no Health from the sim"
        return health[-1].state

    try:
        time.sleep(0.5)
        for role in ("observer", "display"):
            stop(role, engaged=True)
            assert state_after() != "stopped", role
        stop("operator", engaged=True)
        assert state_after() == "stopped"
        for role in ("observer", "display"):
            stop(role, engaged=False)
            assert state_after() == "stopped", role
        stop("operator", engaged=False)
        assert state_after() != "stopped"
    finally:
        sub.undeclare()  # type: ignore[no-untyped-call]
        for session in sessions.values():
            session.close()  # type: ignore[no-untyped-call]


def test_the_participant_display_joins_a_run_with_its_own_certificate() -> None:
    """On a real run (its own credentials): the display's session of the run
    (``Stack.join``) reaches the recorder's key of the comfort rating, and the operator's
    keys not (a participant's page cannot release a stop or take over), while the
    launcher's own session, the operator's, sends a stop."""
    from dammrl.stack.launch import Stack
    from dammrl.stack.options import StackOptions
    from schemas import ComfortRating, EmergencyStop, SessionControl
    from tests.test_schemas import EXAMPLES

    examples = {type(e): e for e in EXAMPLES}
    heard: list[str] = []

    def on_up(hub: zenoh.Session) -> None:
        listener = stack.join("recorder")  # a peer that hears whoever sends
        listener.declare_subscriber("dammrl/session/**",
                                    lambda s: heard.append(str(s.key_expr)))  # fmt: skip
        listener.declare_subscriber("dammrl/safety/**",
                                    lambda s: heard.append(str(s.key_expr)))  # fmt: skip
        display = stack.join("display")
        time.sleep(1.0)
        for message_type in (ComfortRating, SessionControl, EmergencyStop):
            payload = encode(examples[message_type])
            display.put(key("dammrl", message_type), payload)
        time.sleep(1.0)
        heard.append("--")
        hub.put(key("dammrl", EmergencyStop), encode(examples[EmergencyStop]))
        time.sleep(1.0)
        stack.finish()

    stack = Stack(StackOptions(episodes=1, seed=7_000_000, model=(2, 1), port=free_port(),
                               lockstep=True), out=lambda _: None, info=lambda _: None,
                  on_up=on_up)  # fmt: skip
    stack.run()
    display_sent = heard[: heard.index("--")]
    assert display_sent == ["dammrl/session/comfort"], heard
    assert "dammrl/safety/stop" in heard[heard.index("--") :]
