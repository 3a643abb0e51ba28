"""``dammrl stop``: the emergency stop from the operator's console, light to start (no
MuJoCo, no torch: the bus and the messages only)."""

from __future__ import annotations

import time
from dataclasses import dataclass

from schemas import EmergencyStop, Health
from services.common.config import BusSettings
from services.common.security import OPERATOR

ARM_SERVICES = ("sim", "robot")


@dataclass(frozen=True)
class StopReport:
    acknowledged: dict[str, float]  # arm service -> seconds until its Health confirmed
    silent: list[str]  # arm services seen on the bus that did not confirm in time


class StopConsole:
    """The operator's stop on the bus: a session opened once, so that a stop costs no
    start-up (``dammrl stop --console``)."""

    def __init__(self, settings: BusSettings) -> None:
        from services.common.bus import Bus

        self.bus = Bus(settings, OPERATOR).__enter__()
        self.bus.subscribe(Health)
        self.publisher = self.bus.publisher(EmergencyStop)

    def close(self) -> None:
        self.bus.__exit__(None, None, None)

    def send(self, engaged: bool = True, reason: str = "", timeout_s: float = 2.0) -> StopReport:
        """Publish a stop (or its release) until every arm service on the bus confirms it
        in its Health ("stopped", or no longer "stopped"), or ``timeout_s``."""
        acknowledged: dict[str, float] = {}
        start = next_send = time.monotonic()
        while (now := time.monotonic()) - start < timeout_s:
            if now >= next_send:  # repeated: a stop must not hang on one lost message
                stop = EmergencyStop(header=self.publisher.stamp(), engaged=engaged, reason=reason)
                self.publisher.send(stop)
                next_send = now + 0.02
            message = self.bus.receive(0.005)
            if isinstance(message, Health) and self._confirms(message, engaged):
                acknowledged.setdefault(message.service, time.monotonic() - start)
            arms = self._arms()
            if arms and arms <= set(acknowledged) and now - start > 0.1:
                break
        return StopReport(acknowledged, sorted(self._arms() - set(acknowledged)))

    @staticmethod
    def _confirms(health: Health, engaged: bool) -> bool:
        return health.service in ARM_SERVICES and (health.state == "stopped") == engaged

    def _arms(self) -> set[str]:
        return {p for p in self.bus.alive_peers() if p in ARM_SERVICES}


def emergency_stop(
    settings: BusSettings, engaged: bool = True, reason: str = "", timeout_s: float = 2.0
) -> StopReport:
    """One stop (or release), from a session of its own."""
    console = StopConsole(settings)
    try:
        return console.send(engaged, reason, timeout_s)
    finally:
        console.close()
