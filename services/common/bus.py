"""A service's connection to the Zenoh bus: typed publishers, one inbox, health.

Subscriptions fill rings inside Zenoh (no Python runs per message); the service loop
takes them out with :meth:`Bus.receive`, which decodes and validates each one. A payload
that fails is logged once per key and counted; the counts go out in the service's Health
reports (``dammrl status``), and the loop carries on.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator
from types import TracebackType
from typing import Any, Generic, TypeVar

import zenoh

from schemas import (
    DecodeError,
    EmergencyStop,
    Header,
    Health,
    JointCommand,
    Message,
    RobotState,
    decode,
    encode,
    key,
    type_of,
)
from schemas.keys import MAX_MESSAGE_BYTES, downsampling
from schemas.messages import HealthState
from services.common.admission import Admission
from services.common.config import BusSettings
from services.common.runtime import TIME_CRITICAL
from services.common.security import OBSERVER, PEOPLE, ROLES, secure_config_entries

M = TypeVar("M", bound=Message)
MAX_NAME, MAX_PEERS = 64, 32
ARM_LOOP: tuple[type[Message], ...] = (RobotState, JointCommand)
UNLIMITED_ROLES = ("recorder", *PEOPLE)
"""Sessions that take every message that comes (no per-link rate limit): the recorder
keeps everything; people's tools look (replay as fast as possible into a recorder works)."""
"""The loop's messages (100 Hz each way): a late one stalls the arm, so they go first."""
log = logging.getLogger("dammrl.bus")
MAX_DETAIL, MAX_REJECTED = 2000, 63  # Health.detail's and .rejected's bounds (schemas)
CRITICAL_POLL_S = 0.0002
"""How often a waiting time-critical service (the arm's loop) looks at its inbox [s]: a
message waits at most this long on top of the bus (~2-3 % of a core while waiting)."""
POLL_S = 0.001
"""How often any other waiting service looks at its inbox [s]."""
REHEARSAL_LEAD_S = 0.003
"""How long before the next state is due a time-critical service rehearses its work on it
(``Bus.rehearse``) [s]: 1 ms ahead lost its gain to states that came mid-rehearsal, 3 and
5 ms ahead kept it (docs/reference/performance.md)."""


def _priority(message_type: type[Message] | None) -> int:
    """0: an emergency stop; 1: the arm's loop; 2: everything else."""
    if message_type is EmergencyStop:
        return 0
    return 1 if message_type in ARM_LOOP else 2


def zenoh_config(
    settings: BusSettings, role: str = OBSERVER, rate_limits: bool = False
) -> zenoh.Config:
    """The session's Zenoh configuration; with ``settings.credentials``, mutual TLS as
    ``role`` (``settings.role`` wins) and the stack's access control; ``rate_limits``:
    each key's rate per link (the services in the arm's loop and the hub that routes for
    them; a recorder and the tools take everything that comes)."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    # Zenoh drops a larger message while reassembling it, before any subscriber sees it,
    # and a faster one per key and link (schemas.keys.LIMITS)
    config.insert_json5("transport/link/rx/max_message_size", json.dumps(MAX_MESSAGE_BYTES))
    if rate_limits:
        config.insert_json5("downsampling", json.dumps(downsampling(settings.namespace, ROLES)))
    if settings.listen:
        config.insert_json5("listen/endpoints", json.dumps(settings.listen))
    elif settings.credentials is not None and settings.mode == "peer":
        # a peer listens for the others (Zenoh's default is tcp, which TLS-only refuses)
        config.insert_json5("listen/endpoints", json.dumps(["tls/[::]:0"]))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.credentials is not None:
        entries = secure_config_entries(
            settings.credentials, settings.role or role, settings.namespace
        )
        for key_expr, value in entries.items():
            config.insert_json5(key_expr, value)
    return config


class Publisher(Generic[M]):
    """Publishes one message type; stamps the header (clock, sequence number, source)."""

    def __init__(self, bus: Bus, message_type: type[M], key_expr: str, express: bool) -> None:
        self.message_type = message_type
        self.key_expr = key_expr
        self._bus = bus
        urgent = bus.settings.realtime and message_type in ARM_LOOP
        self._zenoh = bus.session.declare_publisher(
            key_expr,
            express=express,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME if urgent else zenoh.Priority.DATA,
        )
        self.seq = 0
        self.count = 0
        self.reported = (0, time.monotonic())  # count and time at the last Health report

    def stamp(self) -> Header:
        """The header of the next message: this clock, the next sequence number, the
        service's name. Build the message with it, then ``send`` it."""
        header = Header(stamp_ns=time.time_ns(), seq=self.seq, source=self._bus.source)
        self.seq += 1
        return header

    def send(self, message: M) -> M:
        """Send a message built with ``stamp()``; return it."""
        self._zenoh.put(encode(message))
        self.count += 1
        return message


class Bus:
    """A service's Zenoh session (a context manager)."""

    def __init__(self, settings: BusSettings, service: str) -> None:
        self.settings = settings
        self.service = service
        self.source = service
        self.namespace = settings.namespace
        self.session: zenoh.Session
        self.rejected: Counter[str] = Counter()
        self.dropped = 0
        self.admission = Admission(settings.namespace)
        # one ring per key, filled by Zenoh's own threads without Python (a payload is
        # copied into Python only when taken); taken out stop first, then the loop's. A
        # waiting loop looks at its rings every ``poll_s``: no Python runs per message, so
        # no other thread wants the GIL and none has to be woken on a busy machine (a
        # callback per message measured worse under load: docs/reference/performance.md)
        self._rings: list[tuple[int, Any]] = []  # (priority, subscriber), by priority
        self._taken: deque[tuple[Message, int]] = deque()  # decoded, not yet received
        self.poll_s = CRITICAL_POLL_S if service in TIME_CRITICAL else POLL_S
        self.arrival_ns = 0  # when the last message receive() returned was taken from its ring
        self._rehearsal: tuple[float, Callable[[], object]] | None = None  # (from when, work)
        self._rehearsing = True  # until a rehearsal fails
        self._publishers: list[Publisher[Any]] = []
        self._started = time.monotonic()
        self._next_health = 0.0
        self._health: Publisher[Health] | None = None
        self._token: Any = None
        self._roster: Any = None
        self._roster_lock = threading.Lock()  # Zenoh's thread writes, the loop reads
        self.peers: set[str] = set()  # services with a liveliness token
        self.missing: dict[str, float] = {}  # services seen alive, now gone: when [Unix s]
        self._sources: dict[type[Message], frozenset[str]] = {}

    def __enter__(self) -> Bus:
        role = self.service if self.service in ROLES else OBSERVER
        limited = role not in UNLIMITED_ROLES
        self.session = zenoh.open(zenoh_config(self.settings, role, rate_limits=limited))
        self._roster = self.session.liveliness().declare_subscriber(
            f"{self.namespace}/alive/*", self._on_liveliness, history=True
        )
        self._health = self.publisher(Health)
        return self

    def declare_alive(self) -> None:
        """Show this service alive (its liveliness token). A service calls it once it has
        subscribed, so "alive" means "hears the bus": the launcher's wait for the recorder
        and the controller's wait for the human then lose no message."""
        if self._token is None:
            alive = f"{self.namespace}/alive/{self.service}"
            self._token = self.session.liveliness().declare_token(alive)

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        close_within(self.session, SESSION_CLOSE_WAIT_S)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        """Remember who went away (and forget it when it is back): a dead service shows
        as missing in every other service's Health, so ``dammrl status`` can name it."""
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        if len(name) > MAX_NAME:
            return
        with self._roster_lock:
            self._update_roster(name, sample.kind == zenoh.SampleKind.DELETE)

    def _update_roster(self, name: str, gone: bool) -> None:
        if gone:
            self.peers.discard(name)
            if len(self.missing) < MAX_PEERS:  # a stray peer's tokens cannot grow it
                self.missing[name] = time.time()
        else:
            self.missing.pop(name, None)
            if len(self.peers) < MAX_PEERS:
                self.peers.add(name)

    def alive_peers(self) -> set[str]:
        """The services whose liveliness token this session sees now."""
        with self._roster_lock:
            return set(self.peers)

    def key(self, message_type: type[Message]) -> str:
        return key(self.namespace, message_type, self.service)

    def publisher(self, message_type: type[M], express: bool = True) -> Publisher[M]:
        publisher = Publisher(self, message_type, self.key(message_type), express)
        self._publishers.append(publisher)
        return publisher

    def subscribe(self, *message_types: type[Message]) -> None:
        """Deliver these message types to :meth:`receive`."""
        for message_type in message_types:
            self.subscribe_key(key(self.namespace, message_type))

    def expect(self, message_type: type[Message], *sources: str) -> None:
        """Accept ``message_type`` only from these publishers (header.source); others are
        rejected, so a stray or misconfigured process cannot drive this service."""
        self._sources[message_type] = frozenset(sources)

    def subscribe_key(self, key_expr: str) -> None:
        """Deliver everything published on ``key_expr`` (wildcards allowed)."""
        ring: zenoh.handlers.RingChannel[zenoh.Sample] = zenoh.handlers.RingChannel(
            self.settings.inbox_size
        )
        subscriber = self.session.declare_subscriber(key_expr, ring)
        message_type = type_of(self.namespace, key_expr.replace("*", "x"))
        self._rings.append((_priority(message_type), subscriber))
        self._rings.sort(key=lambda entry: entry[0])

    def receive_all(self, timeout_s: float) -> list[Message]:
        """Every message waiting (waiting up to ``timeout_s`` for a first one): an
        emergency stop first, then the arm's loop, then the rest, each key in arrival
        order; at most a ring's worth per key (under a flood the loop goes on)."""
        first = self.receive(timeout_s)
        if first is None:
            return []
        self._take()
        messages = [first]
        while self._taken:
            messages.append(self._next())
        return messages

    def receive(self, timeout_s: float | None) -> Message | None:
        """The next valid message, or None after ``timeout_s`` (0: do not wait)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._taken:
            self._take()
            if self._taken:
                break
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                return None
            self._wait(remaining)
        return self._next()

    def rehearse(self, due_s: float, work: Callable[[], object]) -> None:
        """Run ``work`` once while this loop waits, ``REHEARSAL_LEAD_S`` before the next
        message is due (``due_s``, monotonic): the work that message will cause, done on
        the last one and its results dropped (it must change nothing). In the 10 ms
        between two states this machine's caches go cold, and the same work then costs
        several times its warm cost (``benchmarks/idle_gap.py``); rehearsed, the answer
        finds its code and data warm. A later call replaces an earlier one. A rehearsal
        that fails is logged and not tried again: it never stops the loop."""
        if self._rehearsing:
            self._rehearsal = (due_s - REHEARSAL_LEAD_S, work)

    def _wait(self, timeout_s: float | None) -> None:
        """Until the rings may hold something new (at most ``timeout_s``); or a rehearsal."""
        if self._rehearsal is not None and time.monotonic() >= self._rehearsal[0]:
            work, self._rehearsal = self._rehearsal[1], None
            try:
                work()
            except Exception:
                log.exception("a rehearsal failed (the loop goes on without them)")
                self._rehearsing = False
            return
        time.sleep(self.poll_s if timeout_s is None else min(timeout_s, self.poll_s))

    def _next(self) -> Message:
        message, self.arrival_ns = self._taken.popleft()
        return message

    def _take(self) -> None:
        """Move what the rings hold into ``_taken``: admitted, decoded, from the expected
        source; the rest counted."""
        for _, subscriber in self._rings:
            taken = 0
            while (sample := subscriber.try_recv()) is not None:
                taken += 1
                message = self._admit(sample)
                if message is not None:
                    self._taken.append((message, time.time_ns()))
            if taken >= self.settings.inbox_size:
                self.dropped += 1  # the ring was full: older ones were overwritten

    def _admit(self, sample: zenoh.Sample) -> Message | None:
        key_expr = str(sample.key_expr)
        if not self.admission.admit(key_expr, len(sample.payload)):
            return None  # too large for its key: dropped before any copy, counted
        message = self._decode(key_expr, sample.payload.to_bytes())
        if message is None or not self._from_expected_source(message):
            return None
        return message

    def _decode(self, key_expr: str, payload: bytes) -> Message | None:
        message_type = type_of(self.namespace, key_expr)
        if message_type is None:
            return None  # not one of ours (e.g. a liveliness or foreign key)
        try:
            return decode(message_type, payload)
        except DecodeError as exc:
            self.reject(key_expr, str(exc))
            return None

    def _from_expected_source(self, message: Message) -> bool:
        """Checked as the loop takes it (``expect`` may come after ``subscribe``)."""
        allowed = self._sources.get(type(message))
        if allowed is None or message.header.source in allowed:
            return True
        key_expr = self.key(type(message))
        self.reject(key_expr, f"from {message.header.source!r}, expected {sorted(allowed)}")
        return False

    def reject(self, key_expr: str, reason: str) -> None:
        """Count a refused input; log the first few per key, then every 100th."""
        self.rejected[key_expr] += 1
        n = self.rejected[key_expr]
        if n <= 5 or n % 100 == 0:
            log.warning("rejected message #%d on %s: %s", n, key_expr, reason)

    def report_health(
        self, state: HealthState = "ok", detail: str = "", force: bool = False
    ) -> None:
        """Publish Health at most every ``health_period_s`` (call it from the loop)."""
        now = time.monotonic()
        if self._health is None or (now < self._next_health and not force):
            return
        uptime = now - self._started
        rates = {}
        for p in self._publishers:
            count, since = p.reported
            rates[p.key_expr] = (p.count - count) / max(now - since, 1e-3)
            p.reported = (p.count, now)
        counts = (self.rejected + self.admission.refused).most_common(MAX_REJECTED)
        rejected = {why[:200]: n for why, n in counts}
        if self.dropped:
            rejected["inbox overflow (a ring full: older messages overwritten)"] = self.dropped
        with self._roster_lock:
            peers, missing = sorted(self.peers), dict(self.missing)
        self._health.send(
            Health(
                header=self._health.stamp(),
                service=self.service,
                state=state,
                detail=detail[:MAX_DETAIL],
                rejected=rejected,
                rates_hz=rates,
                uptime_s=uptime,
                peers=peers,
                missing=missing,
            )
        )
        self._next_health = now + self.settings.health_period_s


TOOL_CLOSE_WAIT_S = 1.0
"""How long a tool waits for its session to close: a hung peer can hold it 10 s."""


@contextlib.contextmanager
def tool_session(
    settings: BusSettings, say: Callable[[str], None] | None = None
) -> Iterator[zenoh.Session]:
    """A tool's session (status, echo, health check, viewer), closed in bounded time: the
    process is about to end anyway. With ``say``: one line within JOIN_S if it reached no
    stack (a tool never waits in silence)."""
    session = zenoh.open(zenoh_config(settings))
    timer = None
    if say is not None:
        timer = threading.Timer(JOIN_S, lambda: None if linked(session) else say(
            not_joined_line(settings)))  # fmt: skip
        timer.daemon = True
        timer.start()
    try:
        yield session
    finally:
        if timer is not None:
            timer.cancel()
        close_within(session, TOOL_CLOSE_WAIT_S)


JOIN_S = 5.0
"""A client not linked to the stack this long after it started says so."""


def linked(session: zenoh.Session) -> bool:
    """The session reaches a router or a peer (a stack is there and let it in)."""
    return bool(list(session.info.routers_zid()) or list(session.info.peers_zid()))


def not_joined_line(settings: BusSettings) -> str:
    """Why a client may be alone, in one line."""
    where = ", ".join(settings.connect)
    if settings.credentials is None:
        hint = ("is `dammrl up` running on that port? a stack on another machine needs its "
                "--credentials")  # fmt: skip
    else:
        hint = f"with the credentials {settings.credentials}: is the stack up, and are they its?"
    return f"dammrl: nothing answers at {where} ({hint})"


SESSION_CLOSE_WAIT_S = 2.0
"""How long a service waits for its session to close before it goes on to exit."""


def close_within(session: zenoh.Session, wait_s: float) -> None:
    """Close ``session``, waiting at most ``wait_s``: a peer that vanished (a launcher
    killed with -9) can hold a close for many seconds, and the process is ending."""
    closer = threading.Thread(target=_close_quietly, args=(session,), daemon=True)
    closer.start()
    closer.join(wait_s)


def _close_quietly(session: zenoh.Session) -> None:
    with contextlib.suppress(zenoh.ZError):
        session.close()  # type: ignore[no-untyped-call]
