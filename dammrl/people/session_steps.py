"""What a session runs with (``SetUp``), and its steps between its stack runs with the
therapist's console while no reach runs: a block's start (its instructions, then Enter)
and its end (the comfort question, the rest), an emergency stop (the interrupted trial
run again or marked stopped, by the therapist's choice, after the release), every
console line answered at once, and the participant page's connection said at the
console. ``SessionRunner`` (``dammrl.people.session``) is made of these steps and of its stack
runs."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dammrl import __version__
from dammrl.people.console import HELP, Command, Console, Names, parse
from dammrl.people.participants import SessionFolder, now_utc, sha256_of
from dammrl_core.errors import UsageError
from dammrl_core.protocol import Block, Protocol, Trial
from dammrl_core.robot import RobotSettings

if TYPE_CHECKING:
    from dammrl.people.display import ParticipantDisplay

MAX_OUTCOME_S = 30.0


@dataclass(frozen=True)
class SetUp:
    """What a session runs with, from the command line (the protocol says the rest)."""

    mode: str = "virtual"
    intent: str = "simulated"
    """Who decides where a block does not say: simulated, pad, lsl or an installed source."""
    pad_port: str | None = None
    stream: str | None = None
    calibration: Path | None = None
    bus_port: int = 7447
    lockstep: bool = False
    operator: str = "operator"
    """Who runs the session (initials or a staff id), written beside every action."""
    outcome_s: float = 2.0
    """How long each reach's outcome stays on the display before the next reach begins
    [s] (0-30)."""
    rehearsal: bool = False
    """A rehearsal (the simulated patient, before a person sits down): it takes no row of
    the enrolment ledger and runs the order the next participant will run."""
    names: Names | None = None
    """The lab's participant registry: reasons typed at the console are stored without a
    registered name (None: stored as typed, which the console says)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.outcome_s <= MAX_OUTCOME_S:
            raise UsageError(f"--outcome-s {self.outcome_s:g}: the outcome is held 0 to "
                             f"{MAX_OUTCOME_S:g} s")  # fmt: skip

    def fingerprint(self, protocol: Protocol, calibration_sha256: str | None) -> dict[str, Any]:
        """What must not change between the start of a session and its resumption."""
        urdf = RobotSettings().urdf_path
        return {
            "protocol": protocol.name,
            "protocol_version": protocol.version,
            "protocol_sha256": protocol.sha256,
            "dammrl": __version__,
            "mode": self.mode,
            "intent": self.intent,
            "calibration_sha256": calibration_sha256,
            "arm_sha256": sha256_of(urdf),
            "lockstep": self.lockstep,
        }


class SessionSteps:
    """The steps between stack runs (a mixin of ``SessionRunner``, whose state they use)."""

    display: ParticipantDisplay | None
    console: Console
    setup: SetUp
    say: Callable[[str], None]
    protocol: Protocol
    wait: bool
    comfort_timeout_s: float
    session: SessionFolder | None
    blocks: dict[str, Block]
    latched: str | None  # an emergency stop (the console's, the bus's) until released
    pending_comfort: list[tuple[Trial, int, float]]  # rated while no stack ran

    def event(self, what: str, **details: Any) -> dict[str, Any]:
        return {"utc": now_utc(), "who": self.setup.operator, "what": what} | details

    # ---- a block's start and end ------------------------------------------------------
    def _begin(self, session: SessionFolder, trial: Trial, block: Block) -> bool:
        """The block's instructions (again, on a resumption mid-block), then the
        therapist's Enter; False if that can never come (a latched stop, no console)."""
        kind = "practice block" if trial.practice else "block"
        label = f"{kind} {trial.block_position} ({trial.block})"
        if trial.index == 1:
            self.say(f"{label}: {block.instructions}".rstrip(": "))
            session.events.add(self.event("block-start", block=trial.block))
        else:
            self.say(f"{label} goes on at trial {trial.number} (its {trial.index} of "
                     f"{block.trials}): {block.instructions}".rstrip(": "))  # fmt: skip
        if self.display is not None:
            self.display.block(f"{kind.capitalize()} {trial.block_position}", block.instructions)
        return self._wait_ready()

    def _wait_ready(self) -> bool:
        """Wait for Enter (never while a stop is latched); False when the console ends
        with the stop latched."""
        if not self.wait and self.latched is None:
            return True
        ready = threading.Event()

        def enter() -> None:
            if self.latched is not None:
                self.say("console: the emergency stop is latched: type release first")
            else:
                ready.set()

        self.console.route(lambda line: self._between(line, "waiting for Enter", enter=enter))
        page = "" if self.display is None or self.display.pages() else (
            f" (the participant's page is not connected: open {self.display.url})")  # fmt: skip
        self.say("press Enter when the participant is ready" + page)
        try:
            while not ready.wait(0.2):
                if self.console.closed:
                    return self.latched is None
            return True
        finally:
            self.console.route(self._idle)

    def _close_interrupted_block(self, session: SessionFolder, trials: list[Trial]) -> None:
        """A resumption at a block's first trial completes the previous block's end (its
        comfort question and its rest, if a kill interrupted them)."""
        done = session.progress().done
        upcoming = next((t for t in trials if t.number not in done), None)
        if upcoming is not None and upcoming.index == 1 and upcoming.number > 1:
            self._close_block(session, self.blocks[trials[upcoming.number - 2].block], trials)

    def _close_block(self, session: SessionFolder, block: Block, trials: list[Trial]) -> None:
        """Once every trial of ``block`` is done: whatever its end still lacks (its comfort
        rating, its end, its rest), each written to the events as it is done."""
        done = session.progress().done
        mine = [t for t in trials if t.block == block.name]
        if not all(t.number in done for t in mine):
            return
        happened = {e.get("what") for e in session.events.read()[0] if e.get("block") == block.name}
        if "comfort" not in happened and self._asks_comfort():
            self.say(f"the comfort question after {block.name} was not answered yet: asked now")
            answer = self.ask_comfort(session, mine[-1])
            if answer is not None:  # no stack runs: the next run's recording takes it
                self.pending_comfort.append((mine[-1], *answer))
        if "block-end" not in happened:
            session.events.add(self.event("block-end", block=block.name))
        if block.rest_s > 0 and "rest-end" not in happened and len(done) < len(trials):
            started = [e for e in session.events.read()[0]
                       if e.get("what") == "rest" and e.get("block") == block.name]  # fmt: skip
            rested = seconds_since(started[-1].get("utc", "")) if started else 0.0
            self._rest(session, block, block.rest_s - rested, resumed=bool(started))

    def _asks_comfort(self) -> bool:
        return self.display is not None and self.protocol.comfort != "none"

    def ask_comfort(
        self, session: SessionFolder, trial: Trial, interrupted: threading.Event | None = None
    ) -> tuple[int, float] | None:
        """The comfort question on the display (the console's s skips it, ``interrupted``
        ends it: Ctrl-C to a stack that waits on it), logged in the events; (rating,
        seconds it took) or None."""
        display = self.display
        assert display is not None
        if not display.pages():
            self.say(f"no participant page is connected: the comfort question waits on a page "
                     f"nobody sees (open {display.url})")  # fmt: skip
        skipped: list[Command] = []
        cancel = threading.Event()

        def skip(command: Command) -> None:
            skipped.append(command)
            cancel.set()

        if interrupted is not None:
            threading.Thread(target=_relay, args=(interrupted, cancel, self.comfort_timeout_s),
                             daemon=True).start()  # fmt: skip
        previous = self.console.handler
        self.console.route(lambda line: self._between(
            line, "the participant is answering the comfort question (s skips it)",
            {"skip": skip}, fallback=previous,
        ))  # fmt: skip
        try:
            answer = display.ask_comfort(self.comfort_timeout_s, cancel)
        finally:
            self.console.route(previous)
        details: dict[str, Any] = {"rating": None if answer is None else answer[0]}
        if answer is not None:
            details["asked_s"] = round(answer[1], 2)
            self.say(f"comfort after {trial.block}: {answer[0]} of 5")
        elif skipped:
            details["skipped"] = skipped[0].why
            self.say("console: the comfort question skipped")
        else:
            self.say(f"no comfort rating within {self.comfort_timeout_s:.0f} s")
        session.events.add(self.event("comfort", block=trial.block, trial=trial.number,
                                      **details))  # fmt: skip
        return answer

    def _rest(self, session: SessionFolder, block: Block, seconds: float, resumed: bool) -> None:
        """The rest after ``block``: a countdown on the display that the console's s ends
        early; logged as it begins and as it ends."""
        if seconds <= 0.5:
            session.events.add(self.event("rest-end", block=block.name, rested_s=0.0,
                                          early=False, why="its time passed while the "
                                          "session was down"))  # fmt: skip
            return
        ended: list[Command] = []
        over = threading.Event()

        def end_early(command: Command) -> None:
            ended.append(command)
            over.set()

        started = time.monotonic()

        def left() -> str:
            return f"the rest ({seconds - (time.monotonic() - started):.0f} s left; s ends it)"

        session.events.add(self.event("rest", block=block.name, seconds=round(seconds, 1),
                                      **({"resumed": True} if resumed else {})))  # fmt: skip
        self.console.route(lambda line: self._between(
            line, left(), {"skip": end_early, "end-block": end_early},
            enter=lambda: self.say(f"console: {left()}"),
        ))  # fmt: skip
        self.say(f"rest for {seconds:.0f} s{' (what was left of it)' if resumed else ''}: s "
                 "ends it early (Ctrl-C ends the session here; it resumes later)")  # fmt: skip
        if self.display is not None:
            self.display.rest(seconds)
        try:
            over.wait(seconds)
        finally:
            self.console.route(self._idle)
        rested = round(time.monotonic() - started, 1)
        why = {"why": ended[0].why} if ended else {}
        session.events.add(self.event("rest-end", block=block.name, rested_s=rested,
                                      early=bool(ended), **why))  # fmt: skip
        if ended:
            self.say(f"console: the rest ended early after {rested:.0f} s")

    # ---- emergency stops --------------------------------------------------------------
    def heard_stop(self, engaged: bool, reason: str) -> None:
        """An emergency stop or its release on the running stack's bus (the console's x,
        `dammrl stop` from anywhere): the session follows the arm's latch."""
        changed = (self.latched is None) == engaged
        self.latched = reason if engaged else None
        if changed and self.session is not None:
            self.session.events.add(self.event("emergency-stop", engaged=engaged, reason=reason))

    def _after_stop(self, session: SessionFolder, trial: Trial | None, reason: str) -> bool:
        """The session paused by an emergency stop: the trial it interrupted (None: none
        was under way) is run again or marked stopped, by the therapist's choice, once the
        stop is released; False when the console ends first."""
        if self.display is not None and self.latched is not None:
            self.display.stopped()
        if trial is None:
            self.say("the session is paused by the emergency stop: `release` when it is safe; "
                     "then Enter goes on")  # fmt: skip
            return True  # _begin waits for the release and the Enter
        chosen: list[Command] = []
        decided = threading.Event()

        def choose(command: Command) -> None:
            if self.latched is not None:
                self.say("console: the emergency stop is latched: type release first")
                return
            chosen.append(command)
            decided.set()

        self.console.route(lambda line: self._between(
            line, f"trial {trial.number} was stopped: release, then a (again) or s (stopped)",
            {"again": choose, "skip": choose},
        ))  # fmt: skip
        self.say(f"trial {trial.number} is not counted (emergency stop). When it is safe: "
                 f"`release`, then `a` runs trial {trial.number} again or `s` marks it "
                 "stopped")  # fmt: skip
        try:
            while not decided.wait(0.2):
                if self.console.closed:
                    return False
        finally:
            self.console.route(self._idle)
        command = chosen[0]
        session.events.add(self.event("console", trial=trial.number, action=command.action,
                                      why=command.why, after="emergency stop"))  # fmt: skip
        if command.action == "skip":
            session.trials.add(trial_line(trial) | {"result": None, "stopped": reason,
                                                    "why": command.why})  # fmt: skip
            self.say(f"trial {trial.number} marked stopped")
        else:
            self.say(f"trial {trial.number} runs again")
        return True

    # ---- the console between reaches ------------------------------------------------
    def _idle(self, line: str) -> None:
        """A line while no reach can be acted on (a stack starting or ending)."""
        self._between(line, "no reach runs now (a stack is starting or ending): type it "
                      "again once the reach runs")  # fmt: skip

    def _between(
        self,
        line: str,
        now: str,
        acts: dict[str, Callable[[Command], None]] | None = None,
        enter: Callable[[], None] | None = None,
        fallback: Callable[[str], None] | None = None,
    ) -> None:
        """One line while no reach runs: ``acts`` (by action), Enter, the stop and its
        release, help; anything else is refused in one line saying what the session does
        ``now`` (``fallback``: the handler a question interrupted, for the stop)."""
        if not line.strip():
            if enter is not None:
                enter()
            else:
                self.say(f"console: {now}")
            return
        command = self.command(line)
        if command is None:
            return
        act = (acts or {}).get(command.action)
        if act is not None:
            act(command)
        elif command.action in ("stop", "release") and fallback is not None:
            fallback(line)  # a stack runs: the stop goes on its bus
        elif command.action == "stop":
            self._latch(command)
        elif command.action == "release":
            self._release(command)
        elif command.action == "help":
            self.say(HELP)
        else:
            self.say(f"console: {command.action} refused: {now}")

    def command(self, line: str) -> Command | None:
        """The command of ``line`` with its reason as it may be stored; None (said) when it
        is no command."""
        command = parse(line)
        if isinstance(command, str):
            self.say(command)
            return None
        if not command.why:
            return command
        if self.setup.names is not None:
            why, named = self.setup.names.redact(command.why)
            if named:
                self.say("console: the reason named a person of your registry: it is stored "
                         "without the name")  # fmt: skip
            return Command(command.action, why)
        return command

    def _latch(self, command: Command) -> None:
        """The stop typed while no stack runs: nothing is driven, and nothing starts
        until it is released."""
        self.latched = f"emergency stop from {self.setup.operator}" + (
            f": {command.why}" if command.why else "")  # fmt: skip
        if self.session is not None:
            self.session.events.add(self.event("console", action="stop", why=command.why))
        if self.display is not None:
            self.display.stopped()
        self.say("console: emergency stop latched (no stack runs: nothing is driven); the "
                 "session goes on only after release")  # fmt: skip

    def _release(self, command: Command) -> None:
        if self.latched is None:
            self.say("console: no emergency stop is latched")
            return
        self.latched = None
        if self.session is not None:
            self.session.events.add(self.event("console", action="release", why=command.why))
        if self.display is not None:
            self.display.released()
        self.say("console: released (nothing moves before Enter)")

    # ---- the participant's page -------------------------------------------------------
    @contextlib.contextmanager
    def _watching_the_page(self) -> Iterator[None]:
        """Say when the participant's page connects or goes (checked twice a second)."""
        display = self.display
        if display is None:
            yield
            return
        done = threading.Event()

        def watch() -> None:
            shown = -1
            while not done.wait(0.5):
                pages = display.pages()
                if (pages > 0) != (shown > 0) or shown < 0:
                    self.say(f"participant page: connected ({pages})" if pages else
                             f"participant page: not connected (open {display.url})")  # fmt: skip
                shown = pages

        thread = threading.Thread(target=watch, daemon=True)
        thread.start()
        try:
            yield
        finally:
            done.set()
            thread.join(2)


def trial_line(trial: Trial) -> dict[str, Any]:
    """What every line of ``trials.jsonl`` says of its trial."""
    return {"trial": trial.number, "block": trial.block, "block_position": trial.block_position,
            "index": trial.index, "seed": trial.seed, "practice": trial.practice,
            "utc": now_utc()}  # fmt: skip


def seconds_since(utc: str) -> float:
    """Seconds from an event's ``utc`` stamp to now (0 for an unreadable stamp)."""
    try:
        return max(0.0, (datetime.now(UTC) - datetime.fromisoformat(utc)).total_seconds())
    except (TypeError, ValueError):
        return 0.0


def _relay(event: threading.Event, to: threading.Event, within_s: float) -> None:
    """Set ``to`` if ``event`` is set within ``within_s``."""
    if event.wait(within_s):
        to.set()
