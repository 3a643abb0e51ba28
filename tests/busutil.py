"""Helpers for tests on a real Zenoh bus: loopback endpoints, one free port per test."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO

import zenoh

from schemas import DecodeError, Message, decode, key, type_of
from services.common.bus import zenoh_config
from services.common.config import BusSettings

SERVICES = ("sim", "policy", "intent", "controller")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def listener_settings(port: int, namespace: str = "dammrl", mode: str = "peer") -> BusSettings:
    return BusSettings(listen=[endpoint(port)], namespace=namespace, mode=mode)


def client_settings(
    port: int, namespace: str = "dammrl", credentials: Path | None = None
) -> BusSettings:
    scheme = "tcp" if credentials is None else "tls"
    return BusSettings(
        connect=[f"{scheme}/127.0.0.1:{port}"], namespace=namespace, credentials=credentials
    )


def start_service(name: str, port: int, **env: str) -> subprocess.Popen[bytes]:
    """``python -m services.<name>`` connected to the test's endpoint."""
    environment = dict(os.environ)
    environment.update(DAMMRL_BUS_CONNECT=json.dumps([endpoint(port)]))
    environment.update(env)  # the test's settings win (e.g. a TLS endpoint)
    return subprocess.Popen(
        [sys.executable, "-m", f"services.{name}"],
        env=environment,
        stdin=subprocess.DEVNULL,
    )


def start_patient(
    link: Path, port: int, human_model: int, credentials: Path | None = None
) -> subprocess.Popen[bytes]:
    """An emulated pad at ``link`` pressed by a simulated patient answering the stack's
    decision requests (``dammrl sensor emulate --pattern patient``); waits for the pty."""
    bus = ["--connect", endpoint(port)]
    if credentials is not None:
        bus = [
            "--connect",
            endpoint(port).replace("tcp/", "tls/"),
            "--credentials",
            str(credentials),
        ]
    patient = subprocess.Popen(
        [*(sys.executable, "-m", "dammrl", "sensor", "emulate", "--pattern", "patient"),
         *("--patient-model", str(human_model), "--link", str(link)), *bus],
        stdin=subprocess.DEVNULL,
    )  # fmt: skip
    wait_for(link.exists, 30, "the emulated port")
    return patient


def wait_for(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


class Lines:
    """A child's output read line by line on a thread: waits with a timeout (a bare
    ``readline`` on a child that never prints would hang the suite)."""

    def __init__(self, stream: IO[str]) -> None:
        self.lines: list[str] = []
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self.lines.append(line)

    def wait_for(self, text: str, timeout_s: float) -> str:
        """The first line containing ``text``; an AssertionError showing every line read
        when none came within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if found := next((line for line in list(self.lines) if text in line), None):
                return found
            time.sleep(0.05)
        raise AssertionError(f"no line with {text!r} in {timeout_s} s: {self.lines[-20:]}")


class Observer:
    """A test's own session: listens on the endpoint and collects decoded messages."""

    def __init__(
        self,
        port: int,
        namespace: str = "dammrl",
        connect: bool = False,
        credentials: Path | None = None,
    ) -> None:
        self.namespace = namespace
        # a router hub, like the launcher: it brokers for peers until they are linked
        # directly; or (connect) one more peer joining a stack that listens on ``port``
        settings = (
            client_settings(port, namespace, credentials)
            if connect
            else listener_settings(port, namespace, "router")
        )
        self.session = zenoh.open(zenoh_config(settings))
        self.received: list[Message] = []
        self._subscriber = self.session.declare_subscriber(f"{namespace}/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        message_type = type_of(self.namespace, str(sample.key_expr))
        if message_type is None:
            return
        with contextlib.suppress(DecodeError):  # the fuzzer's garbage is seen here too
            self.received.append(decode(message_type, sample.payload.to_bytes()))

    def of(self, message_type: type[Message]) -> list[Message]:
        return [m for m in list(self.received) if isinstance(m, message_type)]

    def put(self, message_type: type[Message], payload: bytes) -> None:
        self.session.put(key(self.namespace, message_type, "fuzz"), payload)

    def close(self) -> None:
        self.session.close()  # type: ignore[no-untyped-call]


class Stack:
    """The virtual stack's four services as processes, connected to ``port``; ``env`` for
    all of them, ``env_of`` for some only (as on machines set up apart)."""

    def __init__(
        self, port: int, env_of: Mapping[str, Mapping[str, str]] | None = None, **env: str
    ) -> None:
        self.port, self.env, self.env_of = port, env, env_of or {}
        self.processes = {name: self._start(name) for name in SERVICES}

    def _start(self, name: str) -> subprocess.Popen[bytes]:
        return start_service(name, self.port, **(self.env | dict(self.env_of.get(name, {}))))

    def kill(self, name: str) -> None:
        self.processes[name].send_signal(signal.SIGKILL)
        self.processes[name].wait()

    def restart(self, name: str) -> None:
        self.processes[name] = self._start(name)

    def alive(self) -> dict[str, bool]:
        return {name: p.poll() is None for name, p in self.processes.items()}

    def stop(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                process.terminate()
        for process in self.processes.values():
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
