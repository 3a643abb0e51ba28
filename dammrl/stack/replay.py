"""``dammrl replay``: a recording back onto the bus, with its original timing.

A replayed JointCommand or TaskGoal must never move an arm by accident: replaying those
topics into a namespace where a sim (or robot) is alive needs ``force``.
"""

from __future__ import annotations

import contextlib
import csv
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from dammrl.stack.recording import Recording
from dammrl.stack.stop import ARM_SERVICES
from dammrl_core.errors import DammrlError, JobFailedError
from dammrl_core.models import ModelSet
from schemas import (
    DecisionRequest,
    EmergencyStop,
    Health,
    ModelChoice,
    RobotState,
    SessionControl,
)
from schemas.keys import key, topic_of
from services.common.bus import JOIN_S, linked, not_joined_line, zenoh_config
from services.common.config import BusSettings
from services.common.security import OBSERVER, roles_publishing

COMMAND_TOPICS = ("robot/command", "task/goal")


@dataclass(frozen=True)
class ReplayOptions:
    rate: float = 1.0  # 1 = real time, 2 = twice as fast, 0 = as fast as possible
    topics: tuple[str, ...] = ()  # topic prefixes relative to the namespace; () = all
    start_s: float = 0.0
    end_s: float | None = None
    loop: bool = False
    force: bool = False


NEVER_REPLAYED = frozenset({topic_of(EmergencyStop), topic_of(SessionControl)})
"""An emergency stop or its release, a pause, a resume or a skip: an operator's act now,
never a recording's."""


def selected(recording: Recording, options: ReplayOptions) -> list[tuple[str, int, bytes]]:
    """(relative topic, log time ns, payload) of the messages to replay, in order."""
    namespace = recording.namespace()
    if not recording.messages:
        return []
    first = recording.messages[0].log_time
    chosen = []
    for message in recording.messages:
        channel = recording.channels[message.channel_id]
        if channel.metadata.get("dammrl.invalid") or not channel.topic.startswith(namespace + "/"):
            continue
        topic = channel.topic[len(namespace) + 1 :]
        if topic in NEVER_REPLAYED:
            continue
        offset_s = (message.log_time - first) * 1e-9
        if options.topics and not topic.startswith(options.topics):
            continue
        if offset_s < options.start_s or (options.end_s is not None and offset_s > options.end_s):
            continue
        chosen.append((topic, message.log_time, message.data))
    return chosen


def replay(
    recording: Recording,
    settings: BusSettings,
    options: ReplayOptions,
    info: Callable[[str], None] = print,
    stop: threading.Event | None = None,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Publish the selected messages under ``settings.namespace``; return how many.
    ``stop`` (e.g. set by Ctrl-C) ends the replay early, a loop included; ``progress(1)``
    after each message."""
    messages = selected(recording, options)
    if not messages:
        raise JobFailedError("nothing to replay: no message matches the topics and time window")
    stop = stop or threading.Event()
    commands = sorted({t for t, _, _ in messages if t.startswith(COMMAND_TOPICS)})
    roles = publishing_roles(sorted({t for t, _, _ in messages}), settings)
    sent = 0
    with contextlib.ExitStack() as sessions:
        opened = {
            role: sessions.enter_context(zenoh.open(zenoh_config(settings, role)))
            for role in sorted(set(roles.values()))
        }
        session = next(iter(opened.values()))
        arms = ArmWatch(session, settings.namespace)
        stop.wait(1.0)  # let the session connect (and learn who is alive) before publishing
        deadline = time.monotonic() + JOIN_S - 1.0
        while not linked(session) and time.monotonic() < deadline and not stop.is_set():
            stop.wait(0.1)
        if not linked(session):  # a replay into the void would look like a success
            raise JobFailedError(not_joined_line(settings).removeprefix("dammrl: "))
        if commands and not options.force:
            arms.wait(2 * settings.health_period_s + 0.5, stop)
            _refuse_if_an_arm_listens(session, settings.namespace, commands, arms)
        publishers = {
            topic: opened[role].declare_publisher(
                f"{settings.namespace}/{topic}",
                express=True,
                congestion_control=zenoh.CongestionControl.BLOCK,  # a replay never drops
            )
            for topic, role in roles.items()
        }
        info(f"replaying {len(messages)} messages on {len(publishers)} topics")
        while not stop.is_set():
            sent += _play_once(messages, publishers, options.rate, stop, progress)
            if not options.loop:
                break
    return sent


def publishing_roles(topics: list[str], settings: BusSettings) -> dict[str, str]:
    """The role whose session publishes each topic. On a plain bus one session does (the
    tool's); on a secured bus each topic goes out as a role the access control lets
    publish it, with that role's certificate from the credentials (``settings.role``
    when set), or the replay is refused before anything is sent: the ACL would drop it."""
    if settings.credentials is None:
        return dict.fromkeys(topics, settings.role or OBSERVER)
    folder = settings.credentials
    roles = {}
    for topic in topics:
        allowed = roles_publishing(topic)
        usable = [r for r in allowed if (folder / f"{r}.key").is_file()]
        if settings.role is not None:
            usable = [settings.role] if settings.role in allowed else []
        if not usable:
            who = f"role {settings.role!r}" if settings.role else f"the credentials in {folder}"
            raise DammrlError(
                f"cannot replay {topic} on this secured bus: {who} may not publish it (only "
                f"{', '.join(allowed) or 'no role'} may); leave it out with --topics"
            )
        roles[topic] = usable[0]
    return roles


def _play_once(
    messages: list[tuple[str, int, bytes]],
    publishers: dict[str, zenoh.Publisher],
    rate: float,
    stop: threading.Event,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Publish ``messages`` once with their recorded spacing over ``rate``; how many
    went out before ``stop``."""
    first, start = messages[0][1], time.perf_counter()
    for sent, (topic, log_time, payload) in enumerate(messages):
        delay = start + (log_time - first) * 1e-9 / rate - time.perf_counter() if rate > 0 else 0
        if stop.wait(delay) if delay > 0 else stop.is_set():
            return sent
        publishers[topic].put(payload)
        if progress is not None:
            progress(1)
    return len(messages)


class ArmWatch:
    """Every sign of a sim or robot on the bus from the moment the replay's session opens:
    its liveliness token, its Health, its states. One liveliness query alone once missed a
    running sim on a loaded machine, and the replay drove it."""

    def __init__(self, session: zenoh.Session, namespace: str) -> None:
        self.seen: set[str] = set()  # "a sim", "a robot", or "an arm" (states of either)
        self.started = time.monotonic()
        alive = [f"{namespace}/alive/{s}" for s in ARM_SERVICES]
        self._subscribers = [
            *(session.liveliness().declare_subscriber(k, self._on_sign, history=True)
              for k in alive),
            *(session.declare_subscriber(key(namespace, Health, s), self._on_sign)
              for s in ARM_SERVICES),
            session.declare_subscriber(key(namespace, RobotState), self._on_sign),
        ]  # fmt: skip

    def _on_sign(self, sample: zenoh.Sample) -> None:  # Zenoh's thread
        if sample.kind == zenoh.SampleKind.PUT:
            name = str(sample.key_expr).rsplit("/", 1)[-1]
            self.seen.add(f"a {name}" if name in ARM_SERVICES else "an arm")

    def wait(self, seconds: float, stop: threading.Event) -> None:
        """Until ``seconds`` after the session opened (an arm's Health comes every
        period), or until a sign came."""
        end = self.started + seconds
        while not self.seen and not stop.is_set() and time.monotonic() < end:
            stop.wait(0.05)


def _refuse_if_an_arm_listens(
    session: zenoh.Session, namespace: str, commands: list[str], arms: ArmWatch
) -> None:
    found = sorted(arms.seen)
    # the watch's history came as the session opened, maybe before it was linked: ask again
    for service in ARM_SERVICES:
        replies = session.liveliness().get(f"{namespace}/alive/{service}", timeout=2.0)
        if any(r.ok is not None for r in replies):
            found.append(f"a {service}")
    if found:
        raise DammrlError(
            f"refusing to replay {', '.join(commands)} into namespace {namespace!r}: "
            f"{found[0]} is alive there and would move. Use --namespace to replay elsewhere, "
            "--topics to leave the commands out, or --force if you mean it."
        )


@dataclass(frozen=True)
class PolicyDecision:
    episode: int
    request: int
    t_s: float
    distance_m: float
    recorded: tuple[int, int] | None  # the M_ij the recorded policy answered with
    proposed: tuple[int, int]  # what the policy under test chooses


def into_policy(recording: Recording, checkpoint: Path) -> list[PolicyDecision]:
    """Offline, no bus: the policy's choice for every recorded decision request.

    The policy sees the recorded end-effector and goal of each request and, as in the
    live stack, its own previous choice as the model in force; its choices sit next to
    the recorded policy's answers (ModelChoice messages carrying the request number).
    """
    from dammrl_core.policy.learned import LearnedPolicy

    policy = LearnedPolicy(ModelSet(), checkpoint)
    answers: dict[tuple[int, int], tuple[int, int]] = {}
    requests: list[DecisionRequest] = []
    for _, decoded in recording.decoded(DecisionRequest, ModelChoice):
        if isinstance(decoded, DecisionRequest):
            requests.append(decoded)
        elif isinstance(decoded, ModelChoice) and decoded.request >= 0:
            answers[(decoded.episode, decoded.request)] = (decoded.human_model, decoded.robot_model)
    decisions, episode = [], None
    for request in requests:
        if request.episode != episode:
            episode = request.episode
            policy.reset()
        ee, goal = np.array(request.ee_pos_m), np.array(request.goal_m)
        choice = policy.decide(ee, goal)
        decisions.append(
            PolicyDecision(
                episode=request.episode,
                request=request.request,
                t_s=request.t_s,
                distance_m=float(np.linalg.norm(goal - ee)),
                recorded=answers.get((request.episode, request.request)),
                proposed=(choice.human_model, choice.robot_model),
            )
        )
    return decisions


def write_decisions(decisions: list[PolicyDecision], out: Path) -> dict[str, float]:
    """CSV of the decisions next to the recorded ones; returns the agreement summary."""
    with open(out, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["episode", "request", "t_s", "distance_m", "recorded_i", "recorded_j",
                         "policy_i", "policy_j"])  # fmt: skip
        for d in decisions:
            recorded = d.recorded or ("", "")
            writer.writerow([d.episode, d.request, f"{d.t_s:.3f}", f"{d.distance_m:.4f}",
                             *recorded, *d.proposed])  # fmt: skip
    compared = [d for d in decisions if d.recorded is not None]
    if not compared:
        return {"decisions": len(decisions), "compared": 0}
    return {
        "decisions": len(decisions),
        "compared": len(compared),
        "agree_i": float(np.mean([d.recorded[0] == d.proposed[0] for d in compared if d.recorded])),
        "agree_j": float(np.mean([d.recorded[1] == d.proposed[1] for d in compared if d.recorded])),
        "agree_both": float(np.mean([d.recorded == d.proposed for d in compared])),
    }
