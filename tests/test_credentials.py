"""Credentials on disk: keys kept private, a local run's credentials found from its port."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from dammrl.cli.common import bus_settings
from services.common.bus import zenoh_config
from services.common.certificates import create_credentials
from services.common.config import BusSettings
from services.common.security import CredentialsError, run_credentials


def test_a_key_readable_by_others_is_refused_with_the_fix(tmp_path: Path) -> None:
    folder = tmp_path / "bus"
    create_credentials(folder, roles=("observer",))
    (folder / "observer.key").chmod(0o644)
    settings = BusSettings(connect=["tls/127.0.0.1:7447"], credentials=folder)
    with pytest.raises(CredentialsError, match=r"readable by others.*chmod 600"):
        zenoh_config(settings)
    (folder / "observer.key").chmod(0o600)
    zenoh_config(settings)  # private again: accepted


def _args(*connect: str) -> argparse.Namespace:
    return argparse.Namespace(connect=list(connect) or None, namespace="dammrl", credentials=None)


def test_a_client_finds_the_local_runs_credentials_from_its_port(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`dammrl up --bus-port 7460` is TLS with credentials of its own: `status`, `echo`,
    `stop` given tcp/ or tls/127.0.0.1:7460 join it without being told where they are."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    tmp_path.chmod(0o700)
    create_credentials(run_credentials(7460))
    for endpoint in ("tcp/127.0.0.1:7460", "tls/127.0.0.1:7460", "tcp/localhost:7460"):
        settings = bus_settings(_args(endpoint))
        assert settings.credentials == run_credentials(7460)
        assert settings.connect == [endpoint.replace("tcp/", "tls/")]
    other = bus_settings(_args("tcp/127.0.0.1:7461"))  # no run there: plain tcp as given
    assert other.credentials is None and other.connect == ["tcp/127.0.0.1:7461"]
    remote = bus_settings(_args("tcp/192.168.1.10:7460"))  # not this machine's run
    assert remote.credentials is None


def test_the_acl_shown_in_the_docs_is_the_one_every_session_loads() -> None:
    import json

    from services.common.security import access_control

    docs = Path(__file__).resolve().parent.parent / "docs" / "zenoh_acl_example.json5"
    text = "\n".join(line for line in docs.read_text().splitlines() if not line.startswith("//"))
    assert json.loads(text) == access_control("dammrl")


def test_credentials_made_before_the_peoples_roles_are_refused_with_what_to_do(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "bus"
    create_credentials(folder, roles=("sim", "tool"))  # one 'tool' role for every person
    settings = BusSettings(connect=["tls/127.0.0.1:7447"], credentials=folder)
    with pytest.raises(CredentialsError, match=r"predates the roles observer, display, operator"
                       r".*dammrl bus init --out NEW_FOLDER"):  # fmt: skip
        zenoh_config(settings, "operator")
    with pytest.raises(CredentialsError, match=r"holds no credentials for role 'controller'"):
        zenoh_config(settings, "controller")
    zenoh_config(settings, "sim")  # its own role is still there
