"""Helpers for session tests: a scripted stack in place of the launcher (its bus echoed to
the session's subscribers), a therapist typing at the console when the session says a
cue, and a participant display that answers without a browser."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

from dammrl.stack.options import StackOptions
from dammrl.stack.stop import StopReport
from dammrl_core.errors import JobFailedError
from schemas import (
    EmergencyStop,
    EpisodeRecorded,
    EpisodeResult,
    Header,
    SessionControl,
    TaskGoal,
    decode,
    encode,
    key,
)

PROTOCOL = """\
format: 1
name: two-blocks
version: "1"
blocks:
  - {name: practice, practice: true, trials: 1, seed: 100}
  - {name: event, trials: 3, seed: 200, condition: {trigger: event}}
  - {name: fixed, trials: 3, seed: 200, condition: {trigger: fixed, policy: fixed, model: [2, 1]}}
"""


def write_protocol(tmp_path: Path, text: str = PROTOCOL) -> Path:
    path = tmp_path / "protocol.yaml"
    path.write_text(text)
    return path


def result(episode: int, seed: int, outcome: str = "success", reason: str = "") -> EpisodeResult:
    return EpisodeResult(  # type: ignore[arg-type]  # outcome: one of the Literal's
        header=Header(stamp_ns=1, seq=episode, source="controller"), episode=episode,
        seed=seed, trigger="event", model=(2, 1), success=outcome == "success", reached=True,
        outcome=outcome, reason=reason or "button pressed", t_total_s=5.0, t_step_mean_s=0.5,
        final_error_m=0.01, n_osc=1, n_osc_per_step=0.1, jerk_isj=1.0, sparc=-2.0, ldlj=-7.0,
        human_error_rate=0.1, n_steps=10, n_decisions=10, button_pressed=True,
        start_m=(0.3, 0, 0), goal_m=(0.5, 0, -0.2),
    )  # fmt: skip


class Sample:
    """What a Zenoh subscriber callback receives, as far as a session reads it."""

    def __init__(self, payload: bytes) -> None:
        self.payload = self
        self._bytes = payload

    def to_bytes(self) -> bytes:
        return self._bytes


class ScriptedStack:
    """The launcher's part a session uses: episodes of the given seeds, each announced to
    the session's subscribers (as the controller's TaskGoal) and its result handed on; a
    stop put on the bus is echoed to them and ends the reach under way (``stopped``), as
    the controller does. ``crash_after`` results in all, it dies as a dead service makes
    it; ``console`` lines are typed (to the run's console) before the reach of the given
    number in all."""

    runs: ClassVar[list[StackOptions]] = []
    crash_after: ClassVar[int | None] = None
    given: ClassVar[int] = 0
    console: ClassVar[dict[int, list[str]]] = {}
    between: ClassVar[dict[int, list[str]]] = {}  # typed after reach N's result (all runs)
    sent: ClassVar[list[Any]] = []
    posterior: ClassVar[tuple[float, float] | None] = None
    ack_after_s: ClassVar[float | None] = None  # the recorder's acknowledgements (None: none)
    stopper: ClassVar[ScriptedStopper | None] = None  # the last run's stop console

    def join(self, role: str) -> ScriptedStack:
        """The display's session of its own role: the same scripted bus."""
        return self

    def __init__(self, options: StackOptions, out: Any, info: Any, on_result: Any,
                 on_up: Any, confirm_recorded: bool) -> None:  # fmt: skip
        self.options, self.on_result, self.on_up = options, on_result, on_up
        self.finishing = False
        self.subscribers: dict[str, list[Callable[[Any], None]]] = {}
        self.stopped = ""

    def stop_console(self) -> ScriptedStopper:
        """The operator's stop console of the run: its stops go on the scripted bus."""
        ScriptedStack.stopper = ScriptedStopper(self)
        return ScriptedStack.stopper

    def declare_subscriber(self, key_expr: str, callback: Callable[[Any], None]) -> object:
        self.subscribers.setdefault(key_expr, []).append(callback)
        return object()

    def put(self, key_expr: str, payload: bytes) -> None:  # the hub session's
        ScriptedStack.sent.append((key_expr, payload))
        if key_expr == key("dammrl", EmergencyStop):
            stop = decode(EmergencyStop, payload)
            self.stopped = stop.reason if stop.engaged else self.stopped
        for callback in self.subscribers.get(key_expr, []):  # the bus echoes it
            callback(Sample(payload))

    def finish(self) -> None:
        self.finishing = True

    def run(self) -> int:
        ScriptedStack.runs.append(self.options)
        assert self.options.episodes is not None and self.options.record is not None
        self.options.record.write_bytes(b"mcap")
        stack_run = self.on_up.__self__
        stack_run.stack = self  # as the launcher is, when it calls on_up
        self.on_up(self)
        stack_run.bus.listening = ScriptedStack.ack_after_s is not None
        for episode in range(1, self.options.episodes + 1):
            if ScriptedStack.crash_after is not None and self.given >= self.crash_after:
                raise JobFailedError("service controller exited unexpectedly with code -9")
            ScriptedStack.given += 1
            seed = self.options.seed + episode - 1
            self.put(key("dammrl", TaskGoal), encode(TaskGoal(
                header=Header(stamp_ns=1, seq=episode, source="controller"), episode=episode,
                seed=seed, start_m=(0.3, 0, 0), goal_m=(0.5, 0, -0.2),
                q_start_rad=(0, 1, 0, 1.6, 0, 0.3))))  # fmt: skip
            outcome, reason = "success", ""
            for line in ScriptedStack.console.get(ScriptedStack.given, []):
                stack_run.console.line(line)
                if line.split()[0] in ("s", "a", "e"):
                    outcome = "skipped"
                if self.stopped:
                    outcome, reason = "stopped", f"emergency stop from tool: {self.stopped}"
                    break
            if ScriptedStack.posterior is not None:  # the policy spoke of the person
                stack_run.bus.posterior = ScriptedStack.posterior
            if ScriptedStack.ack_after_s is not None:
                _acknowledge(stack_run, episode, ScriptedStack.ack_after_s)
            self.on_result(result(episode, seed, outcome, reason))
            for line in ScriptedStack.between.get(ScriptedStack.given, []):
                stack_run.console.line(line)
            deadline = time.monotonic() + 30  # the block closes between two reaches: it
            while not self.finishing and stack_run.closing is not None:  # finishes the run
                assert time.monotonic() < deadline, "the block's close never finished the run"
                time.sleep(0.01)
            if self.finishing:
                break
        return 0


def consoles_controls() -> list[SessionControl]:
    """The SessionControls the session put on the scripted bus for its console (not the
    resume each run's attach sends for its first reach)."""
    from dammrl.people.session import HELD_UNTIL_ATTACHED

    sent = [decode(SessionControl, p) for k, p in ScriptedStack.sent
            if k == key("dammrl", SessionControl)]  # fmt: skip
    return [c for c in sent if c.why != HELD_UNTIL_ATTACHED]


def _acknowledge(stack_run: Any, episode: int, after_s: float) -> None:
    """The recorder's acknowledgement of ``episode``, ``after_s`` from now (on its own
    thread, as the bus delivers it)."""
    ack = EpisodeRecorded(header=Header(stamp_ns=1, seq=episode, source="recorder"),
                          episode=episode, file=stack_run.part.name, result_seq=episode,
                          states=100, complete=True)  # fmt: skip
    later = threading.Timer(after_s, stack_run.bus.recorded.take, args=(ack,))
    later.daemon = True
    later.start()


class ScriptedStopper:
    """A stop console on the scripted bus: each stop published once (the bus echoes it to
    the session), confirmed by the sim at once and by none of ``silent``."""

    silent: ClassVar[list[str]] = []  # arm services that do not confirm

    def __init__(self, stack: ScriptedStack) -> None:
        self.stack, self.sent, self.closed = stack, list[tuple[bool, str]](), False

    def send(self, engaged: bool, reason: str, timeout_s: float) -> StopReport:
        self.sent.append((engaged, reason))
        stop = EmergencyStop(header=Header(stamp_ns=1, seq=len(self.sent), source="operator"),
                             engaged=engaged, reason=reason)  # fmt: skip
        self.stack.put(key("dammrl", EmergencyStop), encode(stop))
        return StopReport({"sim": 0.012}, list(self.silent))

    def close(self) -> None:
        self.closed = True


def reset(stack: type[ScriptedStack]) -> type[ScriptedStack]:
    stack.runs, stack.crash_after, stack.given, stack.stopper = [], None, 0, None
    ScriptedStopper.silent = []
    stack.console, stack.sent, stack.posterior, stack.ack_after_s = {}, [], None, None
    stack.between = {}
    return stack


class Typist:
    """A therapist at the session's console: each rule (cue, line) types ``line`` once the
    session has said something containing ``cue``, in order (None: the console ends
    there); ``every`` answers each time (a cue: its line). What the session said is kept
    in ``said``."""

    def __init__(self, rules: list[tuple[str, str | None]],
                 every: dict[str, str] | None = None) -> None:  # fmt: skip
        reader, writer = os.pipe()
        self.stream = os.fdopen(reader, "r")
        self._writer = os.fdopen(writer, "w")
        self.rules = list(rules)
        self.every = every or {}
        self.said: list[str] = []
        self.lock = threading.Lock()

    def say(self, line: str) -> None:
        with self.lock:
            self.said.append(line)
            if self.rules and self.rules[0][0] in line:
                typed = self.rules.pop(0)[1]
                if typed is None:
                    self.close()
                    return
                self.type(typed)
            for cue, answer in self.every.items():
                if cue in line:
                    self.type(answer)

    def type(self, line: str) -> None:
        if not self._writer.closed:
            self._writer.write(line + "\n")
            self._writer.flush()

    def close(self) -> None:
        if not self._writer.closed:
            self._writer.close()

    def index(self, words: str) -> int:
        """Where the session first said ``words`` (-1: never)."""
        return next((i for i, line in enumerate(self.said) if words in line), -1)


class Killed(BaseException):
    """A kill -9 in the middle of a step (nothing after it runs)."""


class StubDisplay:
    """A participant display without a browser: one page connected; the comfort question
    answered with ``rating`` (or the process killed there), the rest shown (or killed)."""

    url = "http://localhost:0/"

    def __init__(self, rating: int | None = 4, kill_at: str = "") -> None:
        self.rating, self.kill_at = rating, kill_at
        self.shown: list[tuple[str, object]] = []

    def pages(self) -> int:
        return 1

    def ask_comfort(self, timeout_s: float, cancel: threading.Event | None = None
                    ) -> tuple[int, float] | None:  # fmt: skip
        self.shown.append(("comfort", None))
        if self.kill_at == "comfort":
            raise Killed
        return None if self.rating is None else (self.rating, 1.5)

    def rest(self, seconds: float) -> None:
        self.shown.append(("rest", seconds))
        if self.kill_at == "rest":
            raise Killed

    def __getattr__(self, name: str) -> Callable[..., None]:
        def shown(*args: object) -> None:
            self.shown.append((name, args))

        return shown
