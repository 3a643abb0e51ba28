"""``dammrl up``: start the services of a mode as child processes and watch them.

The launcher opens its own Zenoh session (a router) listening on a loopback endpoint;
every service connects to it (and, as Zenoh peers, to each other). It waits for each service's
liveliness token, prints each EpisodeResult, and stops every child on Ctrl-C / SIGTERM,
when the requested episodes are done, or (exit 1) when a service dies on its own.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
from pydantic_settings import BaseSettings

from dammrl.stack.options import (
    StackOptions,
    check_options,
    check_port,
    check_settings,
    run_settings,
    services_of,
)
from dammrl.stack.processes import ServiceProcesses
from dammrl.stack.progress import EpisodeTally, PatientPrompts, Progress, summary
from dammrl.stack.recorded import RECORDED_WAIT_S, RecordedEpisodes
from dammrl.stack.stop import StopConsole
from dammrl_core.errors import (
    Exit,
)
from dammrl_core.settings import environment_of
from schemas import (
    DecodeError,
    EpisodeRecorded,
    EpisodeResult,
    decode,
    key,
)
from services.common.bus import SESSION_CLOSE_WAIT_S, close_within, zenoh_config
from services.common.certificates import create_credentials
from services.common.config import BusSettings
from services.common.runs import RunCard, remove_card, write_card
from services.common.runtime import SignalStop, stopping_on_signals
from services.common.security import OPERATOR, claim_run_credentials, run_credentials


class Stack:
    """One run of the stack: its bus (a router on loopback, with the run's own credentials
    unless given), its services (:class:`ServiceProcesses`), its episodes
    (:class:`EpisodeTally`) and what it says as it goes."""

    def __init__(
        self,
        options: StackOptions,
        out: Callable[[str], None] = print,
        info: Callable[[str], None] = print,
        on_result: Callable[[EpisodeResult], None] | None = None,
        on_up: Callable[[zenoh.Session], None] | None = None,
        confirm_recorded: bool = True,
    ) -> None:
        """``out`` receives the episode results, ``info`` the progress lines; ``on_result``
        each episode's result as it is counted (a session's trial log keeps it at once);
        ``on_up`` the stack's hub session once every service is alive: the operator's
        (the launcher's role; a participant display joins with its own, :meth:`join`).
        ``confirm_recorded``: a recorded run ends only once the recorder confirms its
        episodes on disk, bounded (a session confirms each of its runs itself)."""
        check_options(options)
        self.options = options
        self.info = info
        port = check_port(options.port)
        self.own_credentials = options.credentials is None and not options.insecure
        self.credentials = run_credentials(port) if self.own_credentials else options.credentials
        scheme = "tcp" if self.credentials is None else "tls"
        self.endpoint = f"{scheme}/127.0.0.1:{port}"
        self.processes = ServiceProcesses(options, self.environment, info)
        self.tally = EpisodeTally(options, out, info, on_result)
        self.on_up = on_up
        self.finishing = threading.Event()  # finish(): end the run after the current result
        self.signalled: threading.Event | None = None  # set by Ctrl-C (or a signal) while it runs
        self.joined: list[zenoh.Session] = []  # sessions of other roles (join), closed at the end
        self.recorded: RecordedEpisodes | None = None  # what the recorder confirmed
        if options.record is not None and confirm_recorded:
            self.recorded = RecordedEpisodes(options.record)
        self.recorder_acks: Any = None  # the subscriber feeding it, kept while the run lives
        check_settings(self.services(), self.environment())

    def environment(self) -> dict[str, str]:
        """The children's environment: this one, and the variables of the settings the run
        gives them (built typed, checked as they are built)."""
        env = dict(os.environ)
        for settings in self.service_settings():
            env.update(environment_of(settings))
        env.setdefault("DAMMRL_LOG_LEVEL", "WARNING")  # progress comes from the launcher
        return env

    def service_settings(self) -> list[BaseSettings]:
        """What this run sets for its services, from the command line."""
        o = self.options
        credentials = None if self.credentials is None else self.credentials.resolve()
        # lockstep only when asked: otherwise the environment's
        lockstep: dict[str, Any] = {"lockstep": True} if o.lockstep else {}
        bus = BusSettings(connect=[self.endpoint], namespace=o.namespace, launcher_pid=os.getpid(),
                          credentials=credentials, **lockstep)  # fmt: skip
        return [bus, *run_settings(o)]

    def run(self) -> int:
        """Run until done; the exit code of ``dammrl up``."""
        # a router: it brokers for the services until their direct peer links are up, so a
        # recorder misses nothing a service publishes in its first milliseconds
        settings = BusSettings(
            listen=[self.endpoint],
            namespace=self.options.namespace,
            mode="router",
            credentials=self.credentials,
        )
        self._make_credentials()
        write_card(self.card())  # the tools and emulators beside it find it
        with stopping_on_signals() as stop:
            self.signalled = stop  # a session waiting inside a result's callback looks at it
            # the services' hub, and the operator's session (a session's console, a stop)
            session = zenoh.open(zenoh_config(settings, OPERATOR, rate_limits=True))
            try:
                return self._run_on(session, stop)
            finally:
                self.processes.stop()
                for joined in self.joined:
                    close_within(joined, SESSION_CLOSE_WAIT_S)
                close_within(session, SESSION_CLOSE_WAIT_S)  # a vanished peer can hold it
                remove_card(self.options.port, os.getpid())
                if self.own_credentials and self.credentials is not None:
                    shutil.rmtree(self.credentials, ignore_errors=True)

    def _make_credentials(self) -> None:
        """This run's own credentials (a peer without them cannot join), claimed so that
        its services remove them if the launcher dies."""
        if self.own_credentials:
            assert self.credentials is not None
            shutil.rmtree(self.credentials, ignore_errors=True)
            create_credentials(self.credentials)
            claim_run_credentials(self.credentials)

    def _run_on(self, session: zenoh.Session, stop: SignalStop) -> int:
        results = session.declare_subscriber(key(self.options.namespace, EpisodeResult))
        if self.recorded is not None:
            self.recorder_acks = session.declare_subscriber(
                key(self.options.namespace, EpisodeRecorded), self._recorded
            )
        prompts = None
        if self.options.pad_port is not None and not self.options.json:
            prompts = PatientPrompts(session, self.options.namespace, self.info)
        self.processes.start(session, stop)
        self.info(f"started {', '.join(self.processes.children)} on {self.endpoint}")
        if self.processes.wait_alive(session, stop):
            self.info(f"all services alive: {', '.join(sorted(self.processes.children))}")
            self.info(self.inspect_commands())
        if self.on_up is not None:
            self.on_up(session)
        progress = Progress(session, self.options.namespace, self.info)
        return self._watch(results, stop, progress, prompts)

    def _recorded(self, sample: zenoh.Sample) -> None:
        assert self.recorded is not None
        with contextlib.suppress(DecodeError):
            self.recorded.take(decode(EpisodeRecorded, sample.payload.to_bytes()))

    def _await_recorded(self, stop: SignalStop) -> None:
        """Before the stack stops: wait (bounded) until the recorder confirms the run's
        episodes on disk, their last states and decisions included; say what it did not."""
        episodes = [result.episode for result in self.tally.results]
        if self.recorded is None or not episodes:
            return
        acks = self.recorded.wait(episodes, RECORDED_WAIT_S, stop)
        if stop.is_set():
            return  # asked to stop now: the recorder finishes the file as it is
        if unconfirmed := [e for e in episodes if e not in acks]:
            self.info(f"the recorder did not confirm episode(s) {unconfirmed} on disk within "
                      f"{RECORDED_WAIT_S:g} s (`dammrl recording info` says what the file "
                      "holds)")  # fmt: skip
        for episode, ack in sorted(acks.items()):
            if not ack.complete:
                self.info(f"episode {episode} is recorded without {ack.missing}")

    def card(self) -> RunCard:
        """What a tool needs to join this run: where, how, and the person's input."""
        o = self.options
        credentials = None if self.credentials is None else str(self.credentials.resolve())
        pad = None if o.pad_port is None else os.path.abspath(o.pad_port)
        return RunCard(pid=os.getpid(), port=o.port, endpoint=self.endpoint, namespace=o.namespace,
                       credentials=credentials, pad_port=pad, lsl_stream=o.lsl_stream)  # fmt: skip

    def join(self, role: str) -> zenoh.Session:
        """A session of this process on the run's bus with ``role``'s certificate (the
        participant's display: its comfort rating and nothing else), closed with the run."""
        settings = BusSettings(connect=[self.endpoint], namespace=self.options.namespace,
                               credentials=self.credentials, role=role)  # fmt: skip
        session = zenoh.open(zenoh_config(settings, role))
        self.joined.append(session)
        return session

    def stop_console(self) -> StopConsole:
        """The operator's stop on the run's bus, its session opened now: a stop typed
        later costs no start-up and is repeated until every arm confirms it."""
        return StopConsole(BusSettings(connect=[self.endpoint], namespace=self.options.namespace,
                                       credentials=self.credentials))  # fmt: skip

    def finish(self) -> None:
        """End the run before its last episode (a session ends a block early)."""
        self.finishing.set()

    def services(self) -> tuple[str, ...]:
        return services_of(self.options)

    def inspect_commands(self) -> str:
        """What to type in another terminal to look at this run (clients find its
        credentials and namespace from the port; alone on this machine, they find it
        without one)."""
        at = f"--bus-port {self.options.port}"
        commands = (f"status {at}", f"echo robot/state {at}", f"view {at}")
        lines = [f"  dammrl {command}" for command in commands]
        return "\n".join(["inspect it from another terminal:", *lines,
                          f"stop the arm: dammrl stop {at}"])  # fmt: skip

    def _watch(
        self,
        results: zenoh.Subscriber[zenoh.handlers.Handler[zenoh.Sample]],
        stop: SignalStop,
        progress: Progress,
        prompts: PatientPrompts | None,
    ) -> int:
        """Count the episodes as they end, until the last, a finish or a signal."""
        while not stop.is_set():
            if self.finishing.is_set() or self.tally.done():
                self._await_recorded(stop)
                self.info(summary(self.tally.results))
                return self.tally.verdict()
            self.processes.check()
            if prompts is not None:
                prompts.show()
            progress.check()
            sample = results.try_recv()
            if sample is None:
                time.sleep(0.02)
            elif self.tally.count(sample.payload.to_bytes()) is not None:
                progress.advanced()
        self.info(f"stopping on signal {stop.signum}")
        if (verdict := self.tally.verdict()) != Exit.OK:
            return verdict
        return (
            Exit.OK if self.options.episodes is None else Exit.INTERRUPTED
        )  # open-ended: a signal ends it
