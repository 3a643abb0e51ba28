"""Sessions with people: pseudonymous participants, a folder per sitting, a protocol's
trials run through the service stack, and resumption after any crash.

A session folder holds everything a sitting produced::

    <root>/<participant>/participant.json      id, Latin-square row, current calibration
    <root>/<participant>/ses-01/session.json   protocol (name, version, SHA-256), set-up
    <root>/<participant>/ses-01/protocol.yaml  the protocol as run
    <root>/<participant>/ses-01/trials.jsonl   one line per finished trial (fsync'd)
    <root>/<participant>/ses-01/events.jsonl   who did what and why (start, interruptions,
                                               resumption, rests, the end)
    <root>/<participant>/ses-01/recordings/    part-NN.mcap, one per stack run, never reused
    <root>/<participant>/ses-01/calibration.*  the calibration the session used

A trial counts as done only once its line is in ``trials.jsonl``; whatever stopped a
session (``kill -9`` of the runner or of a service, a lost cable, Ctrl-C), the next
``dammrl session run`` for that participant resumes at the first trial without a line,
after checking that the set-up is the one the session recorded. The recording of an
interrupted run is kept as it is; its trial runs again in a new part.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from dammrl import __version__
from dammrl.console import HELP, Command, Lines, parse
from dammrl.launch import Stack, StackOptions, recording_files, result_dict
from dammrl_core.coadaptation import Targets
from dammrl_core.errors import ConfigurationError, DammrlError, Exit, UsageError
from dammrl_core.protocol import (
    PARTICIPANT_ID,
    Protocol,
    StudyTag,
    Trial,
    load_protocol,
    plan_trials,
)
from dammrl_core.robot import RobotSettings
from schemas import (
    DEFAULT_NAMESPACE,
    ComfortRating,
    DecodeError,
    EmergencyStop,
    EpisodeRecorded,
    EpisodeResult,
    Header,
    Message,
    ModelChoice,
    SessionControl,
    decode,
    encode,
    key,
)
from services.common.security import DISPLAY, OPERATOR

if TYPE_CHECKING:
    from dammrl.display import ParticipantDisplay


def check_participant(participant: str) -> str:
    """``participant`` if it is a pseudonymous id; a UsageError saying what is expected."""
    if not re.match(PARTICIPANT_ID, participant):
        raise UsageError(
            f"participant {participant!r}: give a pseudonymous id such as P012 (1-4 letters, "
            "1-6 digits); names and other personal data are never stored"
        )
    return participant.upper()


def now_utc() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_json(path: Path, content: dict[str, Any]) -> None:
    """Replace ``path`` atomically (a crash leaves the old file or the new one)."""
    temporary = path.with_suffix(path.suffix + ".tmp")
    temporary.write_text(json.dumps(content, indent=2) + "\n")
    with open(temporary, "rb+") as handle:
        os.fsync(handle.fileno())
    temporary.replace(path)


def read_json(path: Path) -> dict[str, Any]:
    try:
        content = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigurationError(f"{path}: unreadable ({exc})") from exc
    if not isinstance(content, dict):
        raise ConfigurationError(f"{path}: not a JSON object")
    return content


class JsonLines:
    """An append-only log, one JSON object a line, each on disk before ``add`` returns. A
    torn last line (a crash mid-write) is skipped when read, and counted."""

    def __init__(self, path: Path):
        self.path = path

    def add(self, entry: dict[str, Any]) -> None:
        with open(self.path, "a", encoding="utf-8") as handle:
            handle.write(json.dumps(entry) + "\n")
            handle.flush()
            os.fsync(handle.fileno())

    def read(self) -> tuple[list[dict[str, Any]], int]:
        """The entries, and how many lines were unreadable."""
        if not self.path.exists():
            return [], 0
        entries, torn = [], 0
        for line in self.path.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                torn += 1
                continue
            if isinstance(entry, dict):
                entries.append(entry)
            else:
                torn += 1
        return entries, torn


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


class Participant:
    """A pseudonymous participant's folder: their Latin-square row (their enrolment
    order), their current calibration and their sessions."""

    def __init__(self, root: Path, participant: str):
        self.id = check_participant(participant)
        self.root = root
        self.folder = root / self.id
        self.file = self.folder / "participant.json"

    def enrol(self) -> dict[str, Any]:
        """Their record, enrolling them (the next row) on first sight."""
        if self.file.exists():
            return read_json(self.file)
        self.root.mkdir(parents=True, exist_ok=True)
        row = sum(1 for p in self.root.glob("*/participant.json"))
        self.folder.mkdir(exist_ok=True)
        record = {"id": self.id, "row": row, "enrolled": now_utc(), "calibration": None}
        write_json(self.file, record)
        return record

    @property
    def policy_folder(self) -> Path:
        """Where ``dammrl adapt --participant`` puts the policy refined for them; their
        sessions load it when it is there."""
        return self.folder / "policy"

    def refined_policy(self) -> Path | None:
        folder = self.policy_folder
        return folder if (folder / "checkpoint.pt").is_file() else None

    def sessions(self) -> list[Path]:
        return sorted(p for p in self.folder.glob("ses-*") if (p / "session.json").exists())

    def keep_calibration(self, calibration: Path) -> Path:
        """Carry ``calibration`` to their later sessions: copied into their folder."""
        kept = self.folder / f"calibration{calibration.suffix or '.json'}"
        if calibration.resolve() != kept.resolve():
            shutil.copyfile(calibration, kept)
        record = read_json(self.file) | {"calibration": kept.name}
        write_json(self.file, record)
        return kept

    def posterior(self) -> tuple[float, float] | None:
        """The human-model posterior their earlier runs ended with (None: none yet)."""
        path = self.folder / "posterior.json"
        if not path.exists():
            return None
        p = read_json(path).get("probabilities")
        if not (isinstance(p, list) and len(p) == 2 and all(isinstance(v, float) for v in p)):
            raise ConfigurationError(f"{path}: no 'probabilities' of the two human models")
        return (p[0], p[1])

    def keep_posterior(self, probabilities: tuple[float, ...], session: str, trials: list[int]
                       ) -> None:  # fmt: skip
        """Carry the posterior a run ended with to the next run and session."""
        write_json(self.folder / "posterior.json", {
            "probabilities": [float(v) for v in probabilities], "session": session,
            "after_trials": trials, "utc": now_utc(),
        })  # fmt: skip

    def calibration(self) -> Path | None:
        """The calibration their last session kept, if any."""
        name = read_json(self.file).get("calibration")
        return None if not name else self.folder / str(name)


@dataclass
class Progress:
    """What a session folder says about its trials."""

    done: dict[int, dict[str, Any]]
    torn: int
    ended: bool


class SessionFolder:
    """One sitting's folder (see the module docstring)."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.manifest = folder / "session.json"
        self.trials = JsonLines(folder / "trials.jsonl")
        self.events = JsonLines(folder / "events.jsonl")
        self.recordings = folder / "recordings"

    @classmethod
    def create(cls, participant: Participant, protocol: Protocol, protocol_file: Path,
               manifest: dict[str, Any]) -> SessionFolder:  # fmt: skip
        number = len(participant.sessions()) + 1
        folder = participant.folder / f"ses-{number:02d}"
        while folder.exists():  # a folder a crash left without its manifest: never reused
            number += 1
            folder = participant.folder / f"ses-{number:02d}"
        folder.mkdir(parents=True)
        session = cls(folder)
        session.recordings.mkdir()
        shutil.copyfile(protocol_file, folder / "protocol.yaml")
        write_json(session.manifest, manifest | {"session": folder.name, "started": now_utc()})
        return session

    def read_manifest(self) -> dict[str, Any]:
        return read_json(self.manifest)

    def progress(self) -> Progress:
        entries, torn = self.trials.read()
        done = {int(e["trial"]): e for e in entries
                if isinstance(e.get("trial"), int) and not e.get("repeat")}  # fmt: skip
        return Progress(done, torn, "ended" in self.read_manifest())

    def next_part(self) -> Path:
        """A recording file no run has used."""
        parts = [int(p.stem.split("-")[1]) for p in self.recordings.glob("part-*.mcap")]
        return self.recordings / f"part-{max(parts, default=0) + 1:02d}.mcap"

    def end(self) -> None:
        write_json(self.manifest, self.read_manifest() | {"ended": now_utc()})


def differences(recorded: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """What changed between the set-up a session recorded and this one."""
    keys = sorted(set(recorded) | set(now))
    return [f"{k}: {recorded.get(k)!r} then, {now.get(k)!r} now" for k in keys
            if recorded.get(k) != now.get(k)]  # fmt: skip


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


class SessionRunner:
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
        self.console = Lines(sys.stdin if console is None else console)
        self.protocol_file = protocol_file
        self.protocol = load_protocol(protocol_file)
        self.blocks = {b.name: b for b in self.protocol.blocks}
        self.setup = setup
        self.say = say
        self.new = new
        self.accept_changes = accept_changes
        self.wait = sys.stdin.isatty() if wait_for_operator is None else wait_for_operator

    def run(self) -> int:
        """Run every trial not yet done; the exit code."""
        record = self.participant.enrol()
        calibration = self._calibration()
        setup = replace(self.setup, calibration=calibration)
        fingerprint = setup.fingerprint(
            self.protocol, None if calibration is None else sha256_of(calibration)
        )
        session = self._session(record, fingerprint)
        if calibration is not None:
            kept = session.folder / f"calibration{calibration.suffix or '.json'}"
            if not kept.exists():
                shutil.copyfile(calibration, kept)
        trials = plan_trials(self.protocol, int(record["row"]))
        self.say(HELP)
        progress = session.progress()
        remaining = [t for t in trials if t.number not in progress.done]
        if not remaining:
            self.say(f"{session.folder}: all {len(trials)} trials are done")
            return Exit.OK
        return self._run_trials(session, setup, trials)

    def _calibration(self) -> Path | None:
        """The calibration given now (kept for later sessions), else the participant's."""
        if self.setup.calibration is not None:
            return self.participant.keep_calibration(self.setup.calibration)
        return self.participant.calibration() if self.setup.intent in ("pad", "lsl") else None

    def _session(self, record: dict[str, Any], fingerprint: dict[str, Any]) -> SessionFolder:
        """The unfinished session to resume (its set-up checked), or a new one."""
        sessions = self.participant.sessions()
        if sessions and not self.new:
            last = SessionFolder(sessions[-1])
            manifest = last.read_manifest()
            if "ended" not in manifest:
                self._check_resumable(last, manifest, fingerprint)
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

    def event(self, what: str, **details: Any) -> dict[str, Any]:
        return {"utc": now_utc(), "who": self.setup.operator, "what": what} | details

    def _run_trials(self, session: SessionFolder, setup: SetUp, trials: list[Trial]) -> int:
        """Run stack after stack until every trial is done (a repeated one runs again)."""
        total = len(trials)
        while remaining := [t for t in trials if t.number not in session.progress().done]:
            group = next(runs(remaining))
            block = self.blocks[group[0].block]
            if group[0].index == 1:
                self._begin_block(session, group[0], block.instructions)
            try:
                code = StackRun(self, session, setup, group, total).run()
            except DammrlError as exc:
                self._stopped(session, group, str(exc))
                raise
            if code != Exit.OK:
                self._stopped(session, group, f"exit code {int(code)}")
                return code
            done = session.progress().done
            if all(t.number in done for t in trials if t.block == block.name):
                session.events.add(self.event("block-end", block=block.name))
                if block.rest_s > 0 and len(done) < total:
                    self._rest(session, block.rest_s)
        session.events.add(self.event("end"))
        session.end()
        if self.display is not None:
            self.display.say("Thank you", "The session is complete.", "good")
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

    def _begin_block(self, session: SessionFolder, trial: Trial, instructions: str) -> None:
        kind = "practice block" if trial.practice else "block"
        self.say(f"{kind} {trial.block_position} ({trial.block}): {instructions}".rstrip(": "))
        if self.display is not None:
            self.display.say(f"{kind.capitalize()} {trial.block_position}", instructions)
        session.events.add(self.event("block-start", block=trial.block))
        if self.wait:
            self.say("press Enter when the participant is ready")
            self.console.get(None)

    def _rest(self, session: SessionFolder, rest_s: float) -> None:
        session.events.add(self.event("rest", seconds=rest_s))
        self.say(f"rest for {rest_s:.0f} s (Ctrl-C ends the session here; it resumes later)")
        if self.display is not None:
            self.display.rest(rest_s)
        else:
            time.sleep(rest_s)


class StackRun:
    """One stack run over trials of one block: each trial logged as its result comes,
    the therapist's console obeyed meanwhile, the comfort asked at the block's end."""

    def __init__(self, runner: SessionRunner, session: SessionFolder, setup: SetUp,
                 group: list[Trial], total: int) -> None:  # fmt: skip
        self.runner, self.session, self.setup = runner, session, setup
        self.group, self.total = group, total
        self.part = session.next_part()
        self.hub: Any = None  # the stack's bus session (the operator's), once it is up
        self.display_bus: Any = None  # the participant display's own (its role), once up
        self.stack: Stack | None = None
        self.episode = 1  # the reach under way (this run counts from 1)
        self.actions: list[dict[str, Any]] = []  # the console's, on the reach under way
        self.paused_since: float | None = None
        self.paused_s = 0.0
        self.again = False  # the reach under way runs again
        self.end_block = False  # the rest of the block is skipped...
        self.end_block_why = ""  # ... by whom and why
        self.running = threading.Event()
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
        setup = self.setup
        prior = runner.participant.posterior()  # what this person's earlier runs said
        checkpoint = runner.participant.refined_policy()  # dammrl adapt --participant
        intent = condition.intent or setup.intent
        person = intent in ("pad", "lsl")
        options = StackOptions(
            mode=setup.mode, episodes=len(group), seed=group[0].seed, model=condition.model,
            trigger=condition.trigger, port=setup.bus_port, record=self.part, study=study,
            intent=None if person else intent,
            pad_port=setup.pad_port if intent == "pad" else None,
            lsl_stream=setup.stream if intent == "lsl" else None,
            calibration=setup.calibration if person else None, lockstep=setup.lockstep,
            prior=prior, checkpoint=checkpoint if condition.model is None else None,
            adaptive=(condition.targets or Targets()) if condition.policy == "adaptive" else None,
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
            self.running.clear()
            self.hub, self.display_bus, self.subscribers = None, None, []
            if self.posterior is not None and self.posterior != prior:
                runner.participant.keep_posterior(self.posterior, self.session.folder.name,
                                                  [t.number for t in self.group])  # fmt: skip
                self.session.events.add(runner.event("posterior", p=list(self.posterior)))

    def attach(self, hub: Any) -> None:
        """The stack is up: the console acts on its bus as the operator; the display
        follows it with a session of its own role, which may send the participant's
        comfort rating and nothing else."""
        self.hub = hub
        if self.runner.display is not None:
            from dammrl.display import BusFeed

            assert self.stack is not None
            self.display_bus = self.stack.join(DISPLAY)
            BusFeed(self.runner.display, DEFAULT_NAMESPACE).attach(self.display_bus)
        self.subscribers = [hub.declare_subscriber(key(DEFAULT_NAMESPACE, ModelChoice),
                                                   self._choice),
                            hub.declare_subscriber(key(DEFAULT_NAMESPACE, EpisodeRecorded),
                                                   self._recorded)]  # fmt: skip
        self.listening = True
        self.running.set()
        threading.Thread(target=self._console, daemon=True).start()

    def _choice(self, sample: Any) -> None:
        """The policy's posterior of this person, as it learns (kept after the run)."""
        with contextlib.suppress(DecodeError):
            choice = decode(ModelChoice, sample.payload.to_bytes())
            if choice.posterior is not None and len(choice.posterior) == 2:
                self.posterior = (choice.posterior[0], choice.posterior[1])

    def _recorded(self, sample: Any) -> None:
        with contextlib.suppress(DecodeError):
            self.recorded.take(decode(EpisodeRecorded, sample.payload.to_bytes()))

    # ---- results --------------------------------------------------------------------
    def keep(self, result: EpisodeResult) -> None:
        trial = self.group[result.episode - 1]
        if self.paused_since is not None:  # skipped while paused
            self.paused_s += time.monotonic() - self.paused_since
            self.paused_since = None
        entry = {"trial": trial.number, "block": trial.block,
                 "block_position": trial.block_position, "index": trial.index,
                 "seed": trial.seed, "practice": trial.practice,
                 "condition": trial.condition.model_dump(mode="json"),
                 "recording": f"recordings/{self._recording().name}", "episode": result.episode,
                 "utc": now_utc(), "result": result_dict(result),
                 "pauses": sum(a["action"] == "pause" for a in self.actions),
                 "paused_s": round(self.paused_s, 2), "actions": self.actions}  # fmt: skip
        if self.again:
            entry["repeat"] = True  # an attempt: the trial is not done
        self.session.trials.add(entry)
        self.runner.say(f"trial {trial.number}/{self.total} ({trial.block} {trial.index}): "
                        f"{result.outcome} in {result.t_total_s:.1f} s"
                        + (": it runs again" if self.again else ""))  # fmt: skip
        self.episode, self.actions, self.paused_s = result.episode + 1, [], 0.0
        last = trial.index == self.runner.blocks[trial.block].trials
        if self.end_block:
            self._skip_rest_of_block(trial)
        if last or self.end_block:
            self._ask_comfort(trial)
        if result.episode == len(self.group) or self.again or self.end_block:
            self._await_recorded()  # the stack stops next
        if self.again or self.end_block:
            assert self.stack is not None
            self.stack.finish()

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

    def _skip_rest_of_block(self, after: Trial) -> None:
        """Log the block's trials after ``after`` as skipped (the operator ended it)."""
        why = self.end_block_why
        for trial in self.group[self.group.index(after) + 1 :]:
            self.session.trials.add({"trial": trial.number, "block": trial.block,
                                     "block_position": trial.block_position,
                                     "index": trial.index, "seed": trial.seed,
                                     "practice": trial.practice, "utc": now_utc(),
                                     "result": None, "skipped": why})  # fmt: skip

    def _ask_comfort(self, trial: Trial) -> None:
        """The participant's comfort after the block, on the display: on the bus (the
        recording keeps it; the block's stack still runs) and in the events."""
        runner = self.runner
        if runner.display is None or runner.protocol.comfort == "none":
            return
        answer = runner.display.ask_comfort(runner.comfort_timeout_s)
        if answer is None:
            self.session.events.add(runner.event("comfort", block=trial.block, rating=None))
            runner.say(f"no comfort rating within {runner.comfort_timeout_s:.0f} s")
            return
        rating, asked_s = answer
        rating_message = ComfortRating(header=self._header(ComfortRating, DISPLAY),
                                       participant=runner.participant.id, block=trial.block,
                                       trial=trial.number, rating=rating,
                                       asked_s=asked_s)  # fmt: skip
        self._send(rating_message, self.display_bus)
        time.sleep(0.2)  # the recorder takes it before the stack stops
        self.session.events.add(runner.event("comfort", block=trial.block, rating=rating,
                                             asked_s=round(asked_s, 2)))  # fmt: skip
        runner.say(f"comfort after {trial.block}: {rating} of 5")

    # ---- the therapist's console ------------------------------------------------------
    def _console(self) -> None:
        while self.running.is_set():
            line = self.runner.console.get(0.2)
            if line is None or not line.strip():
                continue
            command = parse(line)
            if isinstance(command, str):
                self.runner.say(command)
            else:
                self.act(command)

    def act(self, command: Command) -> None:
        """Carry out one console command on the reach under way, logged with who and why."""
        runner, action = self.runner, command.action
        if action == "help":
            runner.say(HELP)
            return
        trial = self.group[min(self.episode, len(self.group)) - 1]
        record = {"action": action, "who": runner.setup.operator, "why": command.why,
                  "utc": now_utc()}  # fmt: skip
        self.actions.append(record)
        self.session.events.add(runner.event("console", trial=trial.number, action=action,
                                             why=command.why))  # fmt: skip
        if action in ("stop", "release"):
            reason = f"{runner.setup.operator}: {command.why}"[:200]
            self._send(EmergencyStop(header=self._header(EmergencyStop), engaged=action == "stop",
                                     reason=reason))  # fmt: skip
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
        elif action in ("skip", "again", "end-block"):
            self.again = action == "again"
            if action == "end-block":
                self.end_block, self.end_block_why = True, f"{runner.setup.operator}: {command.why}"
            self._control(action, command.why)  # each ends the reach; recorded as itself
        runner.say(f"console: {action} (trial {trial.number})")

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

    def _send(self, message: Message, session: Any = None) -> None:
        """Publish ``message`` on ``session`` (default: the operator's, the hub)."""
        session = self.hub if session is None else session
        if session is not None:
            session.put(key(DEFAULT_NAMESPACE, type(message)), encode(message))


def session_table(root: Path, participant: str | None = None) -> list[dict[str, Any]]:
    """One row per session under ``root`` (one participant's, if given)."""
    folders = [Participant(root, participant).folder] if participant else sorted(
        p for p in root.glob("*") if (p / "participant.json").exists()
    )  # fmt: skip
    rows = []
    for folder in folders:
        for path in sorted(folder.glob("ses-*/session.json")):
            session = SessionFolder(path.parent)
            manifest, progress = session.read_manifest(), session.progress()
            total = len(plan_trials(load_protocol(path.parent / "protocol.yaml"),
                                    int(manifest.get("row", 0))))  # fmt: skip
            successes = sum(bool((e.get("result") or {}).get("success"))
                            for e in progress.done.values())  # fmt: skip
            rows.append({"participant": folder.name, "session": path.parent.name,
                         "protocol": manifest["setup"]["protocol"],
                         "started": manifest.get("started", ""),
                         "trials": f"{len(progress.done)}/{total}",
                         "successes": successes,
                         "state": "ended" if progress.ended else "unfinished"})  # fmt: skip
    return rows
