"""Bus settings shared by every service: environment prefix ``DAMMRL_BUS_``.

Lists are JSON in the environment, e.g.
``DAMMRL_BUS_CONNECT='["tcp/192.168.1.20:7447"]'``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Self

from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from dammrl_core.settings import Settings
from schemas import DEFAULT_NAMESPACE


class BusSettings(Settings):
    """How a service joins the Zenoh network."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_BUS_")

    mode: Literal["peer", "client", "router"] = "peer"
    """Zenoh mode: peers talk directly; clients go through a router."""
    listen: list[str] = Field(default_factory=list)
    """Endpoints this service listens on, e.g. ["tcp/0.0.0.0:7447"]."""
    connect: list[str] = Field(default_factory=list)
    """Endpoints this service connects to, e.g. ["tcp/192.168.1.20:7447"]."""
    multicast_scouting: bool = False
    """Discover peers by UDP multicast on the LAN (off: only explicit endpoints)."""
    namespace: str = Field(DEFAULT_NAMESPACE, pattern=r"^[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*$")
    """Key-expression prefix: stacks with different namespaces share a network unseen."""
    health_period_s: float = Field(1.0, ge=0.05, le=60)
    """How often the service publishes its Health [s] (0.05-60 s)."""
    inbox_size: int = Field(256, ge=16, le=65_536)
    """Messages kept per subscribed key until the service loop takes them (a ring: when
    the loop is that far behind, the oldest are overwritten, and counted)."""
    credentials: Path | None = None
    """Folder from `dammrl bus init` (CA, one certificate per role): the session speaks only
    mutual TLS (endpoints tls/HOST:PORT) as its role and enforces the stack's access
    control. None: plain tcp, anyone who reaches the endpoint is on the bus."""
    role: str | None = None
    """Certificate role of this session (default: the service's name; tools: 'tool')."""
    launcher_pid: int | None = Field(None, ge=1, le=4_194_304)  # Linux's largest pid_max
    """The ``dammrl up`` process that started this service (set by it): when that
    process is gone, even killed with -9, the service stops, and removes the run's own
    credentials (those marked with the launcher's pid), which nothing else may use."""
    realtime: bool = True
    """The arm's loop goes first: robot states and commands travel at Zenoh's real-time
    priority (ahead of any other traffic on a link), and the services that close the loop
    (sim or robot, controller) ask the kernel for a higher scheduling priority (nice -10,
    and the same for the session each leads under ``dammrl up``, which Linux shares the
    processors by first; needs root or CAP_SYS_NICE, else logged and skipped)."""
    lockstep: bool = False
    """Run the stack on the robot clock instead of in real time: the sim steps only once
    the controller answered its last state, and the controller answers a state that asked
    for a decision only once the human did. Deterministic (the in-process runner's exact
    twin) and as fast as the bus allows; for simulation only, never for an arm."""
    lockstep_timeout_s: float = Field(4.0, gt=0, le=60)
    """Lockstep: the longest the sim waits for the controller's answer before holding the
    arm as for a stale command; the controller waits half of it for the human, the human
    a quarter for the policy (a bound for a dead service, not for a slow machine) [s]."""

    @model_validator(mode="after")
    def _endpoints_match_the_transport(self) -> Self:
        """With credentials every endpoint is TLS; without, none can be."""
        for endpoint in (*self.listen, *self.connect):
            secure = endpoint.startswith("tls/")
            if self.credentials is not None and not secure:
                raise ValueError(f"endpoint {endpoint!r} must be tls/HOST:PORT with credentials")
            if self.credentials is None and secure:
                raise ValueError(f"endpoint {endpoint!r} needs credentials: {_where(endpoint)}")
        return self


def _where(endpoint: str) -> str:
    """Where the credentials of a stack at ``endpoint`` are (a local run's, or a lab's)."""
    from services.common.security import run_credentials

    host, _, port = endpoint.partition("/")[2].rpartition(":")
    lab = "for a lab's stack, the folder from `dammrl bus init` (a tool's --credentials DIR)"
    if host not in ("127.0.0.1", "localhost", "[::1]") or not port.isdigit():
        return lab
    folder = run_credentials(int(port), create=False)
    return f"a local `dammrl up --bus-port {port}` keeps its own in {folder} while it runs; {lab}"
