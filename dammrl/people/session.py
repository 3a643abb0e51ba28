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

import shutil
import sys
import threading
import time
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
from dammrl.people.run_bus import RunBus
from dammrl.people.session_steps import SessionSteps, SetUp, trial_line
from dammrl.stack.launch import Stack
from dammrl.stack.options import StackOptions, check_stack, recording_files
from dammrl.stack.progress import result_dict
from dammrl.stack.recorded import RECORDED_WAIT_S
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
    EmergencyStop,
    EpisodeResult,
)
from services.common.security import DISPLAY

if TYPE_CHECKING:
    from dammrl.people.display import ParticipantDisplay

__all__ = [  # the session's folders live in dammrl.people.participants; callers import them here
    "JsonLines", "Participant", "SessionFolder", "SessionRunner", "SetUp", "check_participant",
    "session_problems", "session_table",
]  # fmt: skip

PERSON = ("pad", "lsl")
"""Intent sources through which a person decides (they need a device and a calibration)."""
HELD_UNTIL_ATTACHED = "the session, until its console, stop and display are up"
"""Who holds each stack run's first reach back (``StackRun.attach`` resumes it): nothing
moves while a stop typed as the stack starts cannot yet reach its bus."""
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
        outcome_hold_s=setup.outcome_s, first_reach_held_by=HELD_UNTIL_ATTACHED, **run,
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
        self.taken = False  # the therapist decides (t): kept across stack runs until g

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
        self.bus = RunBus(self.part)
        self.console = RunConsole(self)
        self.stack: Stack | None = None
        self.episode = 1  # the reach under way, or the next one (this run counts from 1)
        self.actions: list[dict[str, Any]] = []  # the console's, on the reach under way
        self.paused_since: float | None = None
        self.paused_s = 0.0
        self.again = False  # the reach under way runs again
        self.end_block = False  # the rest of the block is skipped...
        self.end_block_why = ""  # ... by whom and why
        self.stopping: str | None = None  # an emergency stop ends this run: why
        self.stopped_trial: Trial | None = None  # the trial the stop interrupted
        self.closing: threading.Thread | None = None  # the block ended between two reaches

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
                           on_up=self.attach, confirm_recorded=False)  # fmt: skip
        try:
            return self.stack.run()
        finally:
            runner.console.route(runner._idle)
            self.bus.close()
            posterior = self.bus.posterior
            if posterior is not None and posterior != prior:
                runner.participant.keep_posterior(posterior, self.session.folder.name,
                                                  [t.number for t in self.group])  # fmt: skip
                self.session.events.add(runner.event("posterior", p=list(posterior)))

    def attach(self, hub: Any) -> None:
        """The stack is up: the console acts on its bus as the operator; the display
        follows it with a session of its own role, which may send the participant's
        comfort rating and nothing else."""
        runner, bus = self.runner, self.bus
        bus.hub = hub
        if runner.display is not None:
            from dammrl.people.display import BusFeed

            assert self.stack is not None
            bus.display_bus = self.stack.join(DISPLAY)
            runner.display.expect_run(self.places(), condition_intent(self.group[0], self.setup))
            BusFeed(runner.display, DEFAULT_NAMESPACE).attach(bus.display_bus)
        bus.listen(hub, self._stop_heard)
        if runner.latched is not None:  # typed while the stack started: it holds the arm
            bus.send(EmergencyStop(header=bus.header(EmergencyStop), engaged=True,
                                   reason=runner.latched))  # fmt: skip
        # the console acts on the run as soon as the page can show the reach (its first
        # reach is under way already): not after the stop console's own session, which
        # takes a second to open on a busy PC (a stop meanwhile goes on the hub's)
        runner.console.route(self.console.line)
        if self.stack is not None:  # the stop one key away: its session open from now on
            bus.stopper = self.stack.stop_console()
        bus.listening = True
        for trial, rating, asked_s in runner.pending_comfort:  # asked while no stack ran
            bus.comfort(runner.participant.id, trial, rating, asked_s)
        runner.pending_comfort = []
        if runner.taken:  # a new run's intent service and page know nothing of it
            bus.control(1, "take", runner.setup.operator, "taken over in an earlier stack run")
            runner.say("console: the decisions stay taken over (g gives them back)")
        # the first reach may begin (a stop latched meanwhile went out above: it holds on),
        # unless the therapist paused it meanwhile: then their resume lets it begin
        if self.paused_since is None:
            bus.control(1, "resume", runner.setup.operator, HELD_UNTIL_ATTACHED)

    def places(self) -> dict[int, Any]:
        """Each reach's place in the session, for the participant's page."""
        from dammrl.people.display import Place

        blocks = len(self.runner.protocol.blocks)
        trials = self.runner.blocks[self.group[0].block].trials
        return {episode: Place(t.index, trials, t.block_position, blocks, t.practice)
                for episode, t in enumerate(self.group, start=1)}  # fmt: skip

    def _stop_heard(self, stop: EmergencyStop) -> None:
        """An emergency stop (or its release) on the bus, from the console or anyone: the
        session follows it; a stop ends this run (after the stopped reach's result)."""
        reason = f"emergency stop from {stop.header.source}" + (
            f": {stop.reason}" if stop.reason else "")  # fmt: skip
        self.runner.heard_stop(stop.engaged, reason)
        if not stop.engaged or self.stopping is not None:
            return
        self.stopping = reason
        if self.closing is not None:  # the block's close ends the run once it has asked
            return  # (ended now, the session would ask the comfort question again)
        if self.under_way():  # the controller ends the reach: its result ends the run
            later = threading.Timer(STOP_RESULT_WAIT_S, self.finish)  # or, without it, this
            later.daemon = True
            later.start()
        else:
            self.finish()

    def trial(self) -> Trial:
        """The trial under way, or the next one."""
        return self.group[min(self.episode, len(self.group)) - 1]

    def under_way(self) -> bool:
        """A reach of this run was announced and has no result yet."""
        return self.bus.announced >= self.episode

    def finish(self) -> None:
        if self.stack is not None:
            self.stack.finish()

    # ---- results --------------------------------------------------------------------
    def keep(self, result: EpisodeResult) -> None:
        trial = self.group[result.episode - 1]
        paused = self.paused_since is not None  # ended while paused, or as the pause came
        if self.paused_since is not None:
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
        ends = self.again or self.end_block or self.stopping is not None
        self._hold_next(ends, paused)
        if self.end_block:
            self.skip_rest_of_block(trial)
        if (last or self.end_block) and not stopped and not self.again:
            self.ask_comfort(trial)
        if result.episode == len(self.group) or ends:
            self.await_recorded()  # the stack stops next
        if ends:
            self.finish()

    def _hold_next(self, ends: bool, paused: bool) -> None:
        """Hold the run's next reach back before anything that takes time (the comfort
        question, the recorder's confirmation): the controller begins it once the outcome
        has shown. When the run ends (the trial again, the block ended: a stop's latch
        holds on its own), for good; when the reach ended paused, until the resume (a
        pause outlives its reach: typed as the reach ended, it was meant for what
        follows)."""
        if self.episode > len(self.group) or self.stopping is not None:
            return
        operator = self.runner.setup.operator
        if ends:
            why = "the trial runs again" if self.again else "the block ends"
            self.bus.control(self.episode, "pause", operator, why)
        elif paused:
            self.bus.control(self.episode, "pause", operator, "paused as the last reach ended")
            self.paused_since = time.monotonic()

    def await_recorded(self) -> None:
        """Wait (bounded) until the recorder confirms every reach of this run on disk;
        log what it confirmed and say what it did not (the catalogue reports those)."""
        if not self.bus.listening:
            return
        runner, episodes = self.runner, list(range(1, self.episode))
        started = time.monotonic()
        acks = self.bus.recorded.wait(episodes, runner.recorded_wait_s, self.signalled())
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

    def signalled(self) -> threading.Event | None:
        """Ctrl-C (or a signal) to the stack: a question or a wait inside a result's
        callback, which holds the stack's loop, ends at once."""
        return getattr(self.stack, "signalled", None)

    def _recording(self) -> Path:
        """The file the recorder writes now: the part, or its newest continuation after
        a restarted recorder (``part-NN-001.mcap``, ...)."""
        return recording_files(self.part)[-1]

    def skip_rest_of_block(self, after: Trial | None) -> None:
        """Log the block's trials after ``after`` (None: all of this run's) as skipped
        (the operator ended the block)."""
        first = 0 if after is None else self.group.index(after) + 1
        for trial in self.group[first:]:
            skipped = {"result": None, "skipped": self.end_block_why}
            self.session.trials.add(trial_line(trial) | skipped)

    def ask_comfort(self, trial: Trial) -> None:
        """The participant's comfort after the block, on the display: on the bus (the
        recording keeps it; the block's stack still runs) and in the events."""
        runner = self.runner
        if not runner._asks_comfort():
            return
        time.sleep(self.setup.outcome_s)  # the block's last outcome shows as every other
        answer = runner.ask_comfort(self.session, trial, self.signalled())
        if answer is not None:
            self.bus.comfort(runner.participant.id, trial, *answer)
            time.sleep(0.2)  # the recorder takes it before the stack stops


class RunConsole:
    """The therapist's console while a stack runs: each line acted on at once, on the
    reach under way, logged with who and why; between two reaches, ending a trial is
    refused and ending the block acts at once."""

    def __init__(self, run: StackRun) -> None:
        self.run = run

    def line(self, line: str) -> None:
        """One console line while the stack runs."""
        run = self.run
        if not line.strip():
            where = "reach under way" if run.under_way() else "between two reaches"
            run.runner.say(f"console: trial {run.trial().number}, {where} (h for help)")
            return
        command = run.runner.command(line)
        if command is not None:
            self.act(command)

    def act(self, command: Command) -> None:
        """Carry out one console command on the reach under way, logged with who and why."""
        run, action = self.run, command.action
        runner = run.runner
        if action == "help":
            runner.say(HELP)
            return
        trial = run.trial()
        if refusal := self._refusal(action):
            runner.say(f"console: {action} refused: {refusal}")
            return
        run.actions.append({"action": action, "who": runner.setup.operator,
                            "why": command.why, "utc": now_utc()})  # fmt: skip
        run.session.events.add(runner.event("console", trial=trial.number, action=action,
                                            why=command.why))  # fmt: skip
        self._carry_out(command)
        runner.say(f"console: {action} (trial {trial.number})")

    def _refusal(self, action: str) -> str:
        """Why ``action`` cannot be done now ('' when it can)."""
        run = self.run
        if action in ("skip", "again") and not run.under_way():
            return (f"no reach is under way (trial {run.trial().number} begins in a moment): "
                    "type it again once it runs")  # fmt: skip
        if action in ("pause", "resume", "skip", "again", "end-block") and run.stopping:
            return "the emergency stop ends this run"
        return ""

    def _carry_out(self, command: Command) -> None:
        run, action, why = self.run, command.action, command.why
        operator = run.runner.setup.operator
        if action in ("stop", "release"):
            run.bus.stop(action == "stop", f"{operator}: {why}"[:200].rstrip(": "), run.runner.say)
        elif action == "pause" and run.paused_since is None:
            run.paused_since = time.monotonic()
            self._control("pause", why)
        elif action == "resume" and run.paused_since is not None:
            run.paused_s += time.monotonic() - run.paused_since
            run.paused_since = None
            self._control("resume", why)
        elif action in ("take", "give"):
            run.runner.taken = action == "take"
            self._control(action, why)
        elif action in ("forward", "back"):
            small = why.split()[:1] == ["small"]
            self._control("decide", why, u_h=1 if action == "forward" else -1,
                          human_model=2 if small else 1)  # fmt: skip
        elif action == "end-block" and not run.under_way():
            self._end_block_between(command)
        elif action in ("skip", "again", "end-block"):
            run.again = action == "again"
            if action == "end-block":
                run.end_block, run.end_block_why = True, f"{operator}: {why}"
            self._control(action, why)  # each ends the reach; recorded as itself

    def _end_block_between(self, command: Command) -> None:
        """End the block between two reaches: the next reach is held (paused before it
        begins), the block's remaining trials are logged skipped, the comfort question
        asked (on a thread: the console answers meanwhile), then the run ends."""
        run = self.run
        run.end_block, run.end_block_why = True, f"{run.runner.setup.operator}: {command.why}"
        self._control("pause", "the block ends")
        done = run.group[run.episode - 2] if run.episode > 1 else None
        run.skip_rest_of_block(done)

        def close() -> None:
            if done is not None or run.group[0].index > 1:  # a reach of the block was run
                run.ask_comfort(run.group[-1])
            run.await_recorded()
            run.finish()

        run.closing = threading.Thread(target=close, daemon=True)
        run.closing.start()

    def _control(self, action: str, why: str, **decision: int) -> None:
        run = self.run
        run.bus.control(run.episode, action, run.runner.setup.operator, why, **decision)


def condition_intent(trial: Trial, setup: SetUp) -> str:
    """Who decides ``trial``: its block's intent source, else the session's."""
    return trial.condition.intent or setup.intent
