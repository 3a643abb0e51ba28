"""Sessions with people: a protocol's trials run through the service stack for a
pseudonymous participant, the therapist's console answered at every step, and
resumption after any crash.

A session folder holds everything a sitting produced (``dammrl.people.participants``)::

    <root>/<participant>/ses-01/session.json   protocol (name, version, SHA-256), set-up
    <root>/<participant>/ses-01/protocol.yaml  the protocol as run
    <root>/<participant>/ses-01/trials.jsonl   one line per finished trial (fsync'd)
    <root>/<participant>/ses-01/events.jsonl   who did what and why (start, blocks, rests,
                                               comfort, stops, resumption, the end)
    <root>/<participant>/ses-01/recordings/    part-NN.mcap, one per stack run, never reused
    <root>/<participant>/ses-01/calibration.*  the calibration the session used

The flow never surprises: everything that can fail is checked before anyone is enrolled
(``session_problems``); nothing moves before the therapist presses Enter at a block's
start, a resumption or after an emergency stop; a stop ends the reach under way (it is
not counted: run again or marked stopped, the therapist's choice) and the stack with it;
a console line is acted on or refused when it is typed, whatever the session is doing.

A trial counts as done only once its line is in ``trials.jsonl``; whatever stopped a
session (``kill -9`` of the runner or of a service, a lost cable, Ctrl-C), the next
``dammrl session run`` for that participant completes what the end of the last block
left undone (its comfort question, its rest) and resumes at the first trial without a
line, after checking that the set-up is the one the session recorded. The recording of
an interrupted run is kept as it is; its trial runs again in a new part.
"""

from __future__ import annotations

import contextlib
import shutil
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from dammrl.people.console import HELP, Command, Console
from dammrl.people.participants import (
    JsonLines,
    Participant,
    SessionFolder,
    check_participant,
    differences,
    now_utc,
    session_table,
    sha256_of,
)
from dammrl.people.session_steps import SessionSteps, SetUp, trial_line
from dammrl.stack.launch import Stack
from dammrl.stack.options import StackOptions, check_stack, recording_files
from dammrl.stack.progress import result_dict
from dammrl.stack.stop import StopConsole
from dammrl_core.coadaptation import Targets
from dammrl_core.errors import DammrlError, Exit, UsageError
from dammrl_core.protocol import (
    Condition,
    Protocol,
    ProtocolError,
    StudyTag,
    Trial,
    check_protocol,
    load_protocol,
    plan_trials,
)
from dammrl_core.settings import error_line
from schemas import (
    DEFAULT_NAMESPACE,
    ComfortRating,
    DecisionRequest,
    DecodeError,
    EmergencyStop,
    EpisodeRecorded,
    EpisodeResult,
    Header,
    Message,
    ModelChoice,
    SessionControl,
    TaskGoal,
    decode,
    encode,
    key,
)
from services.common.security import DISPLAY, OPERATOR

if TYPE_CHECKING:
    from dammrl.people.display import ParticipantDisplay

__all__ = [  # the session's folders live in dammrl.people.participants; callers import them here
    "JsonLines", "Participant", "SessionFolder", "SessionRunner", "SetUp", "check_participant",
    "session_problems", "session_table",
]  # fmt: skip

STOP_CONFIRM_S = 2.0
"""The console's stop (or release) is sent until every arm confirms it, this long at most."""
PERSON = ("pad", "lsl")
"""Intent sources through which a person decides (they need a device and a calibration)."""
STOP_RESULT_WAIT_S = 3.0
"""After a stop heard mid-reach, how long the stack waits for the controller to end the
reach (``stopped``) before it stops anyway [s]."""


def stack_options(setup: SetUp, condition: Condition, seed: int, episodes: int,
                  calibration: Path | None, **run: Any) -> StackOptions:  # fmt: skip
    """The stack run of ``episodes`` trials of a block from ``seed`` (``run``: what a
    real run adds: its recording, the study tag, the person's prior and policy)."""
    intent = condition.intent or setup.intent
    person = intent in PERSON
    return StackOptions(
        mode=setup.mode, episodes=episodes, seed=seed, model=condition.model,
        trigger=condition.trigger, port=setup.bus_port, intent=intent,
        pad_port=setup.pad_port if intent == "pad" else None,
        lsl_stream=setup.stream if intent == "lsl" else None,
        calibration=calibration if person else None, lockstep=setup.lockstep,
        adaptive=(condition.targets or Targets()) if condition.policy == "adaptive" else None,
        outcome_hold_s=setup.outcome_s, **run,
    )  # fmt: skip


def session_problems(protocol: Protocol, setup: SetUp, calibration: Path | None) -> list[str]:
    """Everything a session of ``protocol`` under ``setup`` would fail on once it runs,
    one plain line each ([] when none): the protocol's own checks (installed intent
    sources, seed ranges), then each block's stack as the launcher checks it before it
    starts (the device and calibration a person needs, every service's settings)."""
    from dammrl_core.intent.source import source_plugins

    problems = check_protocol(protocol, source_plugins())
    if problems:
        return problems
    by_problem: dict[str, list[str]] = {}
    for number, block in enumerate(protocol.blocks, start=1):
        options = stack_options(setup, block.condition, block.seed, block.trials, calibration)
        try:
            check_stack(options)
        except (DammrlError, ValueError) as exc:
            by_problem.setdefault(error_line(exc), []).append(f"{number} ({block.name})")
    return [f"block{'s' if len(blocks) > 1 else ''} {', '.join(blocks)}: {problem}"
            for problem, blocks in by_problem.items()]  # fmt: skip


def runs(trials: list[Trial]) -> Iterator[list[Trial]]:
    """Remaining trials grouped into stack runs: consecutive trials of one block with
    consecutive seeds (a stack runs seeds ``seed``, ``seed + 1``, ...)."""
    group: list[Trial] = []
    for trial in trials:
        if group and (trial.block != group[-1].block or trial.seed != group[-1].seed + 1):
            yield group
            group = []
        group.append(trial)
    if group:
        yield group


Say = Callable[[str], None]

RECORDED_WAIT_S = 15.0
"""How long a stack run waits at its end for the recorder to confirm that each of its
reaches is on disk (``EpisodeRecorded``) before the stack stops [s]. A reach it does not
confirm is logged in ``events.jsonl`` and said; the catalogue reports it."""


class RecordedEpisodes:
    """The recorder's acknowledgements of one stack run's episodes, as they come (a
    complete one supersedes an incomplete one), and a bounded wait for them."""

    def __init__(self, part: Path) -> None:
        self.stem = part.stem  # part-NN: its continuations are part-NN-001.mcap, ...
        self.acks: dict[int, EpisodeRecorded] = {}
        self.changed = threading.Condition()

    def take(self, ack: EpisodeRecorded) -> None:
        """One acknowledgement heard (the recorder of another run's file is not ours)."""
        if ack.header.source != "recorder" or not ack.file.startswith(self.stem):
            return
        with self.changed:
            known = self.acks.get(ack.episode)
            if known is None or not known.complete:
                self.acks[ack.episode] = ack
            self.changed.notify_all()

    def wait(self, episodes: list[int], timeout_s: float) -> dict[int, EpisodeRecorded]:
        """The acknowledgements of ``episodes`` once each is complete, or what came within
        ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self.changed:
            while not all(e in self.acks and self.acks[e].complete for e in episodes):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self.changed.wait(remaining)
            return {e: self.acks[e] for e in episodes if e in self.acks}


class SessionRunner(SessionSteps):
    """Runs (or resumes) a participant's session of a protocol through the stack."""

    def __init__(
        self,
        root: Path,
        participant: str,
        protocol_file: Path,
        setup: SetUp,
        say: Say = print,
        new: bool = False,
        accept_changes: str | None = None,
        wait_for_operator: bool | None = None,
        display: ParticipantDisplay | None = None,
        comfort_timeout_s: float = 120.0,
        console: TextIO | None = None,
        recorded_wait_s: float = RECORDED_WAIT_S,
    ) -> None:
        self.participant = Participant(root, participant)
        self.display = display
        self.comfort_timeout_s = comfort_timeout_s
        self.recorded_wait_s = recorded_wait_s
        self.protocol_file = protocol_file
        self.protocol = load_protocol(protocol_file)
        self.blocks = {b.name: b for b in self.protocol.blocks}
        self.setup = setup
        self.say = say
        self.new = new
        self.accept_changes = accept_changes
        self.wait = sys.stdin.isatty() if wait_for_operator is None else wait_for_operator
        self.console = Console(sys.stdin if console is None else console, self._idle, say)
        self.session: SessionFolder | None = None
        self.resumed = False
        self.latched: str | None = (
            None  # an emergency stop (the console's, the bus's) until released
        )
        self.warned_reasons = False
        self.pending_comfort: list[tuple[Trial, int, float]] = []  # rated while no stack ran

    def problems(self) -> list[str]:
        """What this session would fail on once it runs (``session_problems``), with the
        calibration given or the one the participant has."""
        known = self.participant.calibration() if self.participant.file.exists() else None
        return session_problems(self.protocol, self.setup, self.setup.calibration or known)

    def run(self) -> int:
        """Check everything, then run every trial not yet done; the exit code."""
        problems = self.problems()
        if problems:  # before anyone is enrolled: nothing is written
            raise ProtocolError(self.protocol_file, problems)
        record = self.participant.enrol(self.setup.rehearsal)
        calibration = self._calibration()
        setup = replace(self.setup, calibration=calibration)
        fingerprint = setup.fingerprint(
            self.protocol, None if calibration is None else sha256_of(calibration)
        )
        session = self.session = self._session(record, fingerprint)
        if calibration is not None:
            kept = session.folder / f"calibration{calibration.suffix or '.json'}"
            if not kept.exists():
                shutil.copyfile(calibration, kept)
        trials = plan_trials(self.protocol, int(record["row"]))
        self.say(HELP)
        if self.setup.names is None:
            self.say("console: reasons are stored as typed (events, recordings, BIDS): never "
                     "type a name (--names checks them against your registry)")  # fmt: skip
        progress = session.progress()
        if all(t.number in progress.done for t in trials):
            self.say(f"{session.folder}: all {len(trials)} trials are done")
            return Exit.OK
        with self._watching_the_page():
            return self._run_trials(session, setup, trials)

    def _calibration(self) -> Path | None:
        """The calibration given now (kept for later sessions), else the participant's."""
        if self.setup.calibration is not None:
            return self.participant.keep_calibration(self.setup.calibration)
        return self.participant.calibration() if self.setup.intent in PERSON else None

    def _session(self, record: dict[str, Any], fingerprint: dict[str, Any]) -> SessionFolder:
        """The unfinished session to resume (its set-up checked), or a new one."""
        sessions = self.participant.sessions()
        if sessions and not self.new:
            last = SessionFolder(sessions[-1])
            manifest = last.read_manifest()
            if "ended" not in manifest:
                self._check_resumable(last, manifest, fingerprint)
                self.resumed = True
                return last
        if sessions and "ended" not in (last := SessionFolder(sessions[-1])).read_manifest():
            last.events.add(self.event("left unfinished: a new session started"))
        manifest = {"participant": self.participant.id, "row": record["row"],
                    "setup": fingerprint, "operator": self.setup.operator}  # fmt: skip
        session = SessionFolder.create(self.participant, self.protocol, self.protocol_file,
                                       manifest)  # fmt: skip
        session.events.add(self.event("start", protocol=self.protocol.name))
        self.say(f"new session {session.folder}")
        return session

    def _check_resumable(self, session: SessionFolder, manifest: dict[str, Any],
                         fingerprint: dict[str, Any]) -> None:  # fmt: skip
        """Refuse to resume under another set-up unless the operator says why."""
        changed = differences(manifest.get("setup", {}), fingerprint)
        if changed and self.accept_changes is None:
            raise UsageError(
                f"{session.folder} was started with another set-up ({'; '.join(changed)}): "
                'resume it with --accept-changes "why", or start a new session with --new'
            )
        progress = session.progress()
        session.events.add(self.event("resume", done=len(progress.done),
                                       changed=changed, why=self.accept_changes))  # fmt: skip
        torn = f" ({progress.torn} torn log line skipped)" if progress.torn else ""
        self.say(f"resuming {session.folder}: {len(progress.done)} trials done{torn}")

    def _run_trials(self, session: SessionFolder, setup: SetUp, trials: list[Trial]) -> int:
        """Run stack after stack until every trial is done (a repeated one runs again);
        each block closed (comfort, its end, the rest) before the next begins."""
        total = len(trials)
        self._close_interrupted_block(session, trials)
        ready = self.resumed  # a resumption waits for the therapist's Enter
        while remaining := [t for t in trials if t.number not in session.progress().done]:
            group = next(runs(remaining))
            block = self.blocks[group[0].block]
            if (group[0].index == 1 or ready) and not self._begin(session, group[0], block):
                self._stopped(session, group, "the console closed while the stop was latched")
                return Exit.FAILED
            ready = False
            stack_run = StackRun(self, session, setup, group, total)
            try:
                code = stack_run.run()
            except DammrlError as exc:
                self._stopped(session, group, str(exc))
                raise
            if code != Exit.OK:
                self._stopped(session, group, f"exit code {int(code)}")
                return code
            if stack_run.stopping is not None or self.latched is not None:
                reason = stack_run.stopping or self.latched or "emergency stop"
                if not self._after_stop(session, stack_run.stopped_trial, reason):
                    self._stopped(session, group, "the console closed while the stop was latched")
                    return Exit.FAILED
                ready = True
            self._close_block(session, block, trials)
        session.events.add(self.event("end"))
        session.end()
        if self.display is not None:
            self.display.end()
        unpublished = [f"{t.block}: {rating}" for t, rating, _ in self.pending_comfort]
        if unpublished:
            self.say(f"comfort ({', '.join(unpublished)}) asked after the last stack: kept in "
                     "events.jsonl only (no recording runs to take it)")  # fmt: skip
        self.say(f"session complete: {total} trials in {session.folder}")
        return Exit.OK

    def _stopped(self, session: SessionFolder, group: list[Trial], reason: str) -> None:
        trial = self._first_undone(session, group)
        session.events.add(self.event("stopped", trial=trial, reason=reason))
        self.say(f"stopped at trial {trial}: `dammrl session run` again with the same "
                 f"participant resumes there ({session.folder})")  # fmt: skip

    @staticmethod
    def _first_undone(session: SessionFolder, group: list[Trial]) -> int | None:
        done = session.progress().done
        return next((t.number for t in group if t.number not in done), None)


class StackRun:
    """One stack run over trials of one block: each trial logged as its result comes,
    the therapist's console obeyed meanwhile, the comfort asked at the block's end, and
    the run ended by an emergency stop (after the stopped reach's result)."""

    def __init__(self, runner: SessionRunner, session: SessionFolder, setup: SetUp,
                 group: list[Trial], total: int) -> None:  # fmt: skip
        self.runner, self.session, self.setup = runner, session, setup
        self.group, self.total = group, total
        self.part = session.next_part()
        self.hub: Any = None  # the stack's bus session (the operator's), once it is up
        self.display_bus: Any = None  # the participant display's own (its role), once up
        self.stopper: StopConsole | None = None  # the console's stop, once the stack is up
        self.stack: Stack | None = None
        self.episode = 1  # the reach under way, or the next one (this run counts from 1)
        self.announced = 0  # the last reach the controller announced (its TaskGoal)
        self.actions: list[dict[str, Any]] = []  # the console's, on the reach under way
        self.paused_since: float | None = None
        self.paused_s = 0.0
        self.again = False  # the reach under way runs again
        self.end_block = False  # the rest of the block is skipped...
        self.end_block_why = ""  # ... by whom and why
        self.stopping: str | None = None  # an emergency stop ends this run: why
        self.stopped_trial: Trial | None = None  # the trial the stop interrupted
        self.sent: Counter[type[Message]] = Counter()  # per message type (its key): its seq
        self.posterior: tuple[float, float] | None = None  # the policy's, last heard
        self.subscribers: list[Any] = []
        self.recorded = RecordedEpisodes(self.part)  # what the recorder holds on disk
        self.listening = False  # to the recorder's acknowledgements

    def run(self) -> int:
        runner, group = self.runner, self.group
        condition = group[0].condition
        study = StudyTag(participant=runner.participant.id, session=self.session.folder.name,
                         protocol=runner.protocol.name, version=runner.protocol.version,
                         sha256=runner.protocol.sha256, block=group[0].block,
                         practice=group[0].practice, condition=condition,
                         trials=[t.number for t in group]).model_dump_json()  # fmt: skip
        prior = runner.participant.posterior()  # what this person's earlier runs said
        checkpoint = runner.participant.refined_policy()  # dammrl adapt --participant
        options = stack_options(
            self.setup, condition, group[0].seed, len(group), self.setup.calibration,
            record=self.part, study=study, prior=prior,
            checkpoint=checkpoint if condition.model is None else None,
        )  # fmt: skip
        self.session.events.add(runner.event("run", block=group[0].block,
                                             recording=self.part.name,
                                             trials=[t.number for t in group]))  # fmt: skip
        if options.checkpoint is not None:  # what chose the models: kept with the session
            self.session.events.add(runner.event("policy", refined=str(options.checkpoint)))
        self.stack = Stack(options, out=lambda _: None, info=runner.say, on_result=self.keep,
                           on_up=self.attach)  # fmt: skip
        try:
            return self.stack.run()
        finally:
            runner.console.route(runner._idle)
            self.hub, self.display_bus, self.subscribers = None, None, []
            if self.stopper is not None:
                self.stopper.close()
                self.stopper = None
            if self.posterior is not None and self.posterior != prior:
                runner.participant.keep_posterior(self.posterior, self.session.folder.name,
                                                  [t.number for t in self.group])  # fmt: skip
                self.session.events.add(runner.event("posterior", p=list(self.posterior)))

    def attach(self, hub: Any) -> None:
        """The stack is up: the console acts on its bus as the operator; the display
        follows it with a session of its own role, which may send the participant's
        comfort rating and nothing else."""
        runner = self.runner
        self.hub = hub
        if runner.display is not None:
            from dammrl.people.display import BusFeed

            assert self.stack is not None
            self.display_bus = self.stack.join(DISPLAY)
            runner.display.expect_run(self.places(), condition_intent(self.group[0], self.setup))
            BusFeed(runner.display, DEFAULT_NAMESPACE).attach(self.display_bus)
        self.subscribers = [
            hub.declare_subscriber(key(DEFAULT_NAMESPACE, ModelChoice), self._choice),
            hub.declare_subscriber(key(DEFAULT_NAMESPACE, EpisodeRecorded), self._recorded),
            hub.declare_subscriber(key(DEFAULT_NAMESPACE, EmergencyStop), self._stop_heard),
            hub.declare_subscriber(key(DEFAULT_NAMESPACE, TaskGoal), self._goal_heard),
            hub.declare_subscriber(key(DEFAULT_NAMESPACE, DecisionRequest), self._asked),
        ]
        if self.stack is not None:  # the stop one key away: its session open from now on
            self.stopper = self.stack.stop_console()
        self.listening = True
        for trial, rating, asked_s in runner.pending_comfort:  # asked while no stack ran
            self._send(self._rating(trial, rating, asked_s), self.display_bus)
        runner.pending_comfort = []
        if runner.latched is not None:  # typed while the stack started: it holds the arm
            self._send(EmergencyStop(header=self._header(EmergencyStop), engaged=True,
                                     reason=runner.latched))  # fmt: skip
        runner.console.route(self.line)

    def places(self) -> dict[int, Any]:
        """Each reach's place in the session, for the participant's page."""
        from dammrl.people.display import Place

        blocks = len(self.runner.protocol.blocks)
        trials = self.runner.blocks[self.group[0].block].trials
        return {episode: Place(t.index, trials, t.block_position, blocks, t.practice)
                for episode, t in enumerate(self.group, start=1)}  # fmt: skip

    def _choice(self, sample: Any) -> None:
        """The policy's posterior of this person, as it learns (kept after the run)."""
        with contextlib.suppress(DecodeError):
            choice = decode(ModelChoice, sample.payload.to_bytes())
            if choice.posterior is not None and len(choice.posterior) == 2:
                self.posterior = (choice.posterior[0], choice.posterior[1])

    def _recorded(self, sample: Any) -> None:
        with contextlib.suppress(DecodeError):
            self.recorded.take(decode(EpisodeRecorded, sample.payload.to_bytes()))

    def _goal_heard(self, sample: Any) -> None:
        with contextlib.suppress(DecodeError):
            goal = decode(TaskGoal, sample.payload.to_bytes())
            if goal.header.source == "controller":
                self.announced = max(self.announced, goal.episode)

    def _asked(self, sample: Any) -> None:
        """A decision request: its reach runs (its goal may have gone out before the run
        listened)."""
        with contextlib.suppress(DecodeError):
            request = decode(DecisionRequest, sample.payload.to_bytes())
            if request.header.source == "controller":
                self.announced = max(self.announced, request.episode)

    def _stop_heard(self, sample: Any) -> None:
        """An emergency stop (or its release) on the bus, from the console or anyone: the
        session follows it; a stop ends this run (after the stopped reach's result)."""
        try:
            stop = decode(EmergencyStop, sample.payload.to_bytes())
        except DecodeError:
            return
        reason = f"emergency stop from {stop.header.source}" + (
            f": {stop.reason}" if stop.reason else "")  # fmt: skip
        self.runner.heard_stop(stop.engaged, reason)
        if not stop.engaged or self.stopping is not None:
            return
        self.stopping = reason
        if self.under_way():  # the controller ends the reach: its result ends the run
            later = threading.Timer(STOP_RESULT_WAIT_S, self._finish)  # or, without it, this
            later.daemon = True
            later.start()
        else:
            self._finish()

    def under_way(self) -> bool:
        """A reach of this run was announced and has no result yet."""
        return self.announced >= self.episode

    def _finish(self) -> None:
        if self.stack is not None:
            self.stack.finish()

    # ---- results --------------------------------------------------------------------
    def keep(self, result: EpisodeResult) -> None:
        trial = self.group[result.episode - 1]
        if self.paused_since is not None:  # skipped while paused
            self.paused_s += time.monotonic() - self.paused_since
            self.paused_since = None
        stopped = result.outcome == "stopped"
        entry = trial_line(trial) | {
            "condition": trial.condition.model_dump(mode="json"),
            "recording": f"recordings/{self._recording().name}", "episode": result.episode,
            "result": result_dict(result),
            "pauses": sum(a["action"] == "pause" for a in self.actions),
            "paused_s": round(self.paused_s, 2), "actions": self.actions}  # fmt: skip
        if self.again or stopped:
            entry["repeat"] = True  # an attempt: the trial is not done
        if stopped:
            entry["stopped"] = result.reason
            self.stopping = self.stopping or result.reason
            self.stopped_trial = trial
            if self.runner.latched is None:  # its stop was not heard: the arm's latch holds
                self.runner.heard_stop(True, result.reason)
        self.session.trials.add(entry)
        outcome = "stopped: not counted" if stopped else result.outcome
        self.runner.say(f"trial {trial.number}/{self.total} ({trial.block} {trial.index}): "
                        f"{outcome} after {result.t_total_s:.1f} s"
                        # why it held: the person, the plan or a fault of the stack
                        + (f" ({result.reason})" if result.outcome == "hold" else "")
                        + (": it runs again" if self.again else ""))  # fmt: skip
        self.episode, self.actions, self.paused_s = result.episode + 1, [], 0.0
        last = trial.index == self.runner.blocks[trial.block].trials
        if self.end_block:
            self._skip_rest_of_block(trial)
        if (last or self.end_block) and not stopped:
            self._ask_comfort(trial)
        ends = self.again or self.end_block or self.stopping is not None
        if result.episode == len(self.group) or ends:
            self._await_recorded()  # the stack stops next
        if ends:
            self._finish()

    def _await_recorded(self) -> None:
        """Wait (bounded) until the recorder confirms every reach of this run on disk;
        log what it confirmed and say what it did not (the catalogue reports those)."""
        if not self.listening:
            return
        runner, episodes = self.runner, list(range(1, self.episode))
        started = time.monotonic()
        acks = self.recorded.wait(episodes, runner.recorded_wait_s)
        trial = {e: self.group[e - 1].number for e in episodes}
        partial = {trial[e]: a.missing for e, a in acks.items() if not a.complete}
        unconfirmed = [trial[e] for e in episodes if e not in acks]
        self.session.events.add(runner.event(
            "recorded", recording=self.part.name, episodes=episodes,
            confirmed=[trial[e] for e, a in acks.items() if a.complete], partial=partial,
            unconfirmed=unconfirmed, unconfirmed_episodes=[e for e in episodes if e not in acks],
            waited_s=round(time.monotonic() - started, 3),
        ))  # fmt: skip
        if unconfirmed:
            runner.say(f"the recorder did not confirm trial(s) {unconfirmed} on disk within "
                       f"{runner.recorded_wait_s:g} s: the catalogue will report them")  # fmt: skip
        for number, missing in partial.items():
            runner.say(f"trial {number} is recorded without {missing}")

    def _recording(self) -> Path:
        """The file the recorder writes now: the part, or its newest continuation after
        a restarted recorder (``part-NN-001.mcap``, ...)."""
        return recording_files(self.part)[-1]

    def _skip_rest_of_block(self, after: Trial | None) -> None:
        """Log the block's trials after ``after`` (None: all of this run's) as skipped
        (the operator ended the block)."""
        first = 0 if after is None else self.group.index(after) + 1
        for trial in self.group[first:]:
            skipped = {"result": None, "skipped": self.end_block_why}
            self.session.trials.add(trial_line(trial) | skipped)

    def _ask_comfort(self, trial: Trial) -> None:
        """The participant's comfort after the block, on the display: on the bus (the
        recording keeps it; the block's stack still runs) and in the events."""
        runner = self.runner
        if not runner._asks_comfort():
            return
        time.sleep(self.setup.outcome_s)  # the block's last outcome shows as every other
        answer = runner.ask_comfort(self.session, trial)
        if answer is not None:
            self._send(self._rating(trial, *answer), self.display_bus)
            time.sleep(0.2)  # the recorder takes it before the stack stops

    def _rating(self, trial: Trial, rating: int, asked_s: float) -> ComfortRating:
        header = self._header(ComfortRating, DISPLAY)
        return ComfortRating(header=header, participant=self.runner.participant.id,
                             block=trial.block, trial=trial.number, rating=rating,
                             asked_s=asked_s)  # fmt: skip

    # ---- the therapist's console ------------------------------------------------------
    def line(self, line: str) -> None:
        """One console line while the stack runs."""
        if not line.strip():
            where = "reach under way" if self.under_way() else "between two reaches"
            self.runner.say(f"console: trial {self.trial().number}, {where} (h for help)")
            return
        command = self.runner.command(line)
        if command is not None:
            self.act(command)

    def trial(self) -> Trial:
        """The trial under way, or the next one."""
        return self.group[min(self.episode, len(self.group)) - 1]

    def act(self, command: Command) -> None:
        """Carry out one console command on the reach under way, logged with who and why;
        between two reaches, ending a trial is refused and ending the block acts at once."""
        runner, action = self.runner, command.action
        if action == "help":
            runner.say(HELP)
            return
        trial = self.trial()
        if action in ("skip", "again") and not self.under_way():
            runner.say(f"console: {action} refused: no reach is under way (trial {trial.number} "
                       "begins in a moment): type it again once it runs")  # fmt: skip
            return
        if action in ("pause", "resume", "skip", "again", "end-block") and self.stopping:
            runner.say(f"console: {action} refused: the emergency stop ends this run")
            return
        record = {"action": action, "who": runner.setup.operator, "why": command.why,
                  "utc": now_utc()}  # fmt: skip
        self.actions.append(record)
        self.session.events.add(runner.event("console", trial=trial.number, action=action,
                                             why=command.why))  # fmt: skip
        if action in ("stop", "release"):
            self._stop(action, f"{runner.setup.operator}: {command.why}"[:200].rstrip(": "))
        elif action == "pause" and self.paused_since is None:
            self.paused_since = time.monotonic()
            self._control("pause", command.why)
        elif action == "resume" and self.paused_since is not None:
            self.paused_s += time.monotonic() - self.paused_since
            self.paused_since = None
            self._control("resume", command.why)
        elif action in ("take", "give"):
            self._control(action, command.why)
        elif action in ("forward", "back"):
            small = command.why.split()[:1] == ["small"]
            self._control("decide", command.why, u_h=1 if action == "forward" else -1,
                          human_model=2 if small else 1)  # fmt: skip
        elif action == "end-block" and not self.under_way():
            self._end_block_between(command)
        elif action in ("skip", "again", "end-block"):
            self.again = action == "again"
            if action == "end-block":
                self.end_block, self.end_block_why = True, f"{runner.setup.operator}: {command.why}"
            self._control(action, command.why)  # each ends the reach; recorded as itself
        runner.say(f"console: {action} (trial {trial.number})")

    def _end_block_between(self, command: Command) -> None:
        """End the block between two reaches: the next reach is held (paused before it
        begins), the block's remaining trials are logged skipped, the comfort question
        asked (on a thread: the console answers meanwhile), then the run ends."""
        self.end_block, self.end_block_why = True, f"{self.runner.setup.operator}: {command.why}"
        self._control("pause", "the block ends")
        done = self.group[self.episode - 2] if self.episode > 1 else None
        self._skip_rest_of_block(done)

        def close() -> None:
            if done is not None or self.group[0].index > 1:  # a reach of the block was run
                self._ask_comfort(self.group[-1])
            self._await_recorded()
            self._finish()

        threading.Thread(target=close, daemon=True).start()

    def _control(self, action: str, why: str, **decision: int) -> None:
        self._send(SessionControl(header=self._header(SessionControl), episode=self.episode,
                                  action=action, who=self.runner.setup.operator, why=why,
                                  **decision))  # fmt: skip

    def _header(self, message_type: type[Message], source: str = OPERATOR) -> Header:
        """The next header of ``message_type``: one sequence per key and publisher, as
        the recorder counts loss."""
        self.sent[message_type] += 1
        seq = self.sent[message_type] - 1
        return Header(stamp_ns=time.time_ns(), seq=seq, source=source)

    def _stop(self, action: str, reason: str) -> None:
        """The emergency stop (or its release), sent until every arm confirms it (as
        ``dammrl stop --console`` does: no start-up, repeated while unconfirmed)."""
        if self.stopper is None:  # the stack is not up yet
            self._send(EmergencyStop(header=self._header(EmergencyStop),
                                     engaged=action == "stop", reason=reason))  # fmt: skip
            return
        report = self.stopper.send(action == "stop", reason, STOP_CONFIRM_S)
        for service, seconds in sorted(report.acknowledged.items()):
            self.runner.say(f"console: {action} confirmed by {service} after "
                            f"{seconds * 1000:.0f} ms")  # fmt: skip
        for service in report.silent or ([] if report.acknowledged else ["no arm"]):
            self.runner.say(f"console: {service} did not confirm the {action} within "
                            f"{STOP_CONFIRM_S:.0f} s: use the hardware stop")  # fmt: skip

    def _send(self, message: Message, session: Any = None) -> None:
        """Publish ``message`` on ``session`` (default: the operator's, the hub)."""
        session = self.hub if session is None else session
        if session is not None:
            session.put(key(DEFAULT_NAMESPACE, type(message)), encode(message))


def condition_intent(trial: Trial, setup: SetUp) -> str:
    """Who decides ``trial``: its block's intent source, else the session's."""
    return trial.condition.intent or setup.intent
