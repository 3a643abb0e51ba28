"""Identity on the bus from the transport: mutual TLS with one certificate per role, and a
Zenoh access-control list that lets each role publish only its own keys.

A lab creates its credentials once (``dammrl bus init``): a CA and, per role, a
certificate whose Common Name is the role. Every session then proves its role with its
certificate (mutual TLS: a peer without one from the lab CA cannot even connect), and
every session enforces the same ACL on what its peers send it (peer mode links services
directly, so an ACL held only by a router would be bypassed). The payload's
``header.source`` stays as information; it decides nothing.

Besides the services, three roles match the people around the arm: an *observer* reads
(viewers, ``status``, ``echo``, health checks), the participant's *display* sends only
their comfort rating, and the *operator* (``dammrl stop``, the launcher and its
therapist's console) stops the arm, releases a stop and controls the session. Only the
operator's certificate can release a stop or take the decisions over: give a viewer's or
a display's machine only ``ca.pem`` and its own role's files.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from dammrl_core.errors import DammrlError

OBSERVER, DISPLAY, OPERATOR = "observer", "display", "operator"

# the keys (under the namespace) each role may publish, besides its health and liveliness
PUBLISHES: dict[str, tuple[str, ...]] = {
    "sim": ("robot/state", "task/refused"),
    "robot": ("robot/state", "task/refused"),  # the real arm (stage S3): the sim's contract
    "controller": (
        "robot/command", "intent/request", "controller/step", "task/goal", "task/result",
    ),
    "intent": ("intent", "intent/evidence", "sensor/sample", "sensor/chunk"),
    "policy": ("policy/model",),
    "recorder": ("recorder/episode",),  # that an episode is on disk
    OBSERVER: (),  # viewers, status, echo, health checks, emulators that only listen
    DISPLAY: ("session/comfort",),  # the participant's display: their comfort rating
    # `dammrl stop`, the launcher and its therapist's console: a stop and its release,
    # pause, resume, skip and taking the decisions over
    OPERATOR: ("safety/stop", "session/control"),
}  # fmt: skip
ROLES = tuple(PUBLISHES)
PEOPLE = (OBSERVER, DISPLAY, OPERATOR)
"""The roles of people's tools (every other role is a service's)."""
RETIRED_ROLES = ("tool",)
"""Roles of earlier credentials: one 'tool' certificate served every person's tool."""


def roles_publishing(topic: str) -> tuple[str, ...]:
    """The roles allowed to publish ``topic`` (relative to the namespace), in ROLES order."""
    if topic.startswith("health/"):
        role = topic.removeprefix("health/")
        return (role,) if role in PUBLISHES else ()
    return tuple(role for role, topics in PUBLISHES.items() if topic in topics)


CA_FILE = "ca.pem"
_EVERY_MESSAGE = [
    "put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
]  # fmt: skip


class CredentialsError(DammrlError):
    """Credentials that are missing or unusable (the message names the file)."""


# ---- credentials ---------------------------------------------------------------------
def private_folder(create: bool = True) -> Path:
    """This user's private runtime folder of dammrl (``$XDG_RUNTIME_DIR/dammrl``), where
    local runs keep their credentials and cards; checked private (``create``: made so)."""
    base = os.environ.get("XDG_RUNTIME_DIR") or os.path.join(
        tempfile.gettempdir(), f"dammrl-{os.getuid()}"
    )
    private = Path(base) / "dammrl"
    if create:
        for folder in (Path(base), private):
            folder.mkdir(exist_ok=True, mode=0o700)
            _check_private(folder)
    return private


def run_credentials(port: int, create: bool = True) -> Path:
    """Where ``dammrl up`` keeps the credentials of the stack on loopback ``port``: in the
    user's private runtime folder, so only this user's tools find and read them."""
    return private_folder(create) / f"bus-{port}"


OWNER_FILE = "launcher.pid"
"""In a run's own credentials: the pid of the ``dammrl up`` they belong to."""


def claim_run_credentials(folder: Path) -> None:
    """Mark ``folder`` as this process's run's own credentials."""
    (folder / OWNER_FILE).write_text(f"{os.getpid()}\n")


def run_owner(folder: Path) -> int | None:
    """The pid of the launcher whose run owns ``folder`` (None: not a run's own)."""
    try:
        return int((folder / OWNER_FILE).read_text())
    except (OSError, ValueError):
        return None


def stale_run_credentials(folder: Path) -> bool:
    """Whether ``folder`` holds a run's own credentials whose launcher is gone."""
    owner = run_owner(folder)
    if owner is None:
        return False
    try:
        os.kill(owner, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        return False
    return False


def remove_run_credentials(folder: Path, launcher_pid: int) -> bool:
    """Remove ``folder`` if it is the run's own of ``launcher_pid``; whether it was."""
    if run_owner(folder) != launcher_pid:
        return False
    shutil.rmtree(folder, ignore_errors=True)
    return True


def _check_private(folder: Path) -> None:
    """Refuse a folder another user owns or may write (it could swap our credentials)."""
    info = folder.lstat()
    if folder.is_symlink() or info.st_uid != os.getuid() or info.st_mode & 0o022:
        raise CredentialsError(
            f"{folder} is not private to you (owner uid {info.st_uid}, mode "
            f"{oct(info.st_mode & 0o777)}): remove it or set XDG_RUNTIME_DIR"
        )


def _check_key(path: Path) -> None:
    """Refuse a private key that others may read, or that another user owns (as ssh does):
    whoever reads it can join the bus as its role."""
    info = path.stat()
    if info.st_mode & 0o077 or os.getuid() not in (info.st_uid, 0):  # root reads any
        raise CredentialsError(
            f"{path} is readable by others or not yours (mode {oct(info.st_mode & 0o777)}, "
            f"owner uid {info.st_uid}): whoever reads it joins the bus as its role; "
            f"`chmod 600 {path}` (and keep its folder private)"
        )


def _missing(credentials: Path, role: str, name: str) -> str:
    """Why ``credentials`` cannot serve ``role`` (its file ``name`` is missing), and what
    to do."""
    retired = [r for r in RETIRED_ROLES if (credentials / f"{r}.pem").is_file()]
    if retired and role in PEOPLE:
        return (f"{credentials} predates the roles {', '.join(PEOPLE)} (it holds one "
                f"{retired[0]!r} certificate for every person's tool): create new "
                "credentials with `dammrl bus init --out NEW_FOLDER`, give each machine its "
                "roles")  # fmt: skip
    return (f"{credentials / name} is missing: {credentials} holds no credentials for role "
            f"{role!r}; create them with `dammrl bus init --out {credentials}`, or copy "
            f"{role}.pem and {role}.key there from the lab's folder")  # fmt: skip


# ---- Zenoh configuration ------------------------------------------------------------------
def tls_settings(credentials: Path, role: str) -> dict[str, Any]:
    """``transport/link/tls`` for ``role``: its certificate both ways, mutual TLS."""
    files = {name: credentials / name for name in (CA_FILE, f"{role}.pem", f"{role}.key")}
    for name, path in files.items():
        if not path.is_file():
            raise CredentialsError(_missing(credentials, role, name))
    _check_key(files[f"{role}.key"])
    cert, key = str(files[f"{role}.pem"]), str(files[f"{role}.key"])
    return {
        "root_ca_certificate": str(files[CA_FILE]),
        "listen_certificate": cert,
        "listen_private_key": key,
        "connect_certificate": cert,
        "connect_private_key": key,
        "enable_mtls": True,
        # identity is the role certificate signed by the lab CA, not a host name: peers
        # link to each other at whatever address gossip announces (LAN, loopback, IPv6)
        "verify_name_on_connect": False,
    }


def access_control(namespace: str) -> dict[str, Any]:
    """The stack's ACL: a role may publish only its own keys (and its health, liveliness);
    every role may subscribe to and receive everything under the namespace."""
    rules: list[dict[str, Any]] = [
        _rule("read", ["ingress"], ["declare_subscriber", "declare_liveliness_subscriber",
                                    "liveliness_query"], [f"{namespace}/**"]),
        _rule("deliver", ["egress"], _EVERY_MESSAGE, [f"{namespace}/**"]),
    ]  # fmt: skip
    policies = []
    for role, topics in PUBLISHES.items():
        keys = [f"{namespace}/{t}" for t in (*topics, f"health/{role}")]
        rules.append(_rule(f"publish_{role}", ["ingress"], ["put"], keys))
        alive = [f"{namespace}/alive/{role}", f"{namespace}/alive/{role}/**"]
        rules.append(_rule(f"alive_{role}", ["ingress"], ["liveliness_token", "reply"], alive))
        rule_ids = ["read", "deliver", f"publish_{role}", f"alive_{role}"]
        policies.append({"id": f"role_{role}", "rules": rule_ids, "subjects": [role]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": role, "cert_common_names": [role]} for role in ROLES],
        "policies": policies,
    }


def _rule(
    rule_id: str, flows: list[str], messages: list[str], key_exprs: list[str]
) -> dict[str, Any]:
    return {
        "id": rule_id, "permission": "allow", "flows": flows, "messages": messages,
        "key_exprs": key_exprs,
    }  # fmt: skip


def secure_config_entries(credentials: Path, role: str, namespace: str) -> dict[str, str]:
    """The Zenoh config entries (key -> JSON) that make a session speak only mutual TLS as
    ``role`` and enforce the ACL."""
    if role not in PUBLISHES:
        raise CredentialsError(f"role {role!r} is not one of {list(ROLES)}")
    return {
        "transport/link/protocols": json.dumps(["tls"]),
        "transport/link/tls": json.dumps(tls_settings(credentials, role)),
        "access_control": json.dumps(access_control(namespace)),
    }
