"""Sessions as a BIDS dataset (Brain Imaging Data Structure, v1.11: its motion datatype):
what a lab shares and what the field's tools read.

One BIDS *run* per reach (every attempt of every trial), found through the catalogue and
read from its recording:

* ``motion/``: the arm's kinematics at the state rate on the robot's clock: the
  end-effector's position and velocity and the six joint angles (``_motion.tsv`` with
  its ``_channels.tsv`` and ``_motion.json``);
* ``_events.tsv`` beside it: the reach's start, each decision asked and made (the
  command, the radius, the source, its confidence), each micro-step and its trigger, the
  therapist's acts and the outcome;
* ``beh/``: the person's raw input where it was recorded: the pad's pressure and a
  wearable's samples (``_physio.tsv.gz``), on the same clock.

``participants.tsv`` lists the pseudonymous ids only (dammrl stores no names), and
``sessions.tsv`` each participant's sessions with their protocol. Times: seconds from
the reach's first state (robot clock); a message without a robot time of its own is
placed by its receipt time, interpolated between the states around it.
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dammrl import __version__
from dammrl.catalogue import CatalogueError, query
from dammrl.recording import Recording, read_recording
from dammrl_core.robot import RobotSettings
from schemas import (
    DecisionRequest,
    EpisodeResult,
    Intent,
    RobotState,
    SensorSample,
    SessionControl,
    SignalChunk,
    StepEvent,
)

BIDS_VERSION = "1.11.0"
TASK = "reach"
TRACKING_SYSTEM = "dammrl"
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Reach:
    """One row of the catalogue's trials: where a reach is recorded."""

    participant: str
    session: str
    trial: int
    attempt: int
    block: str
    recording: str
    episode: int
    start_ns: int
    end_ns: int


def export(
    root: Path, out: Path, authors: list[str] | None = None, license_: str | None = None
) -> dict[str, int]:
    """Write the BIDS dataset of every session in the catalogue under ``root`` to ``out``
    (replaced; the dataset's ``Authors`` and ``License`` as given); the count of
    participants, sessions and runs written."""
    _clear(out)
    reaches = list(_reaches(root))
    joints = RobotSettings().load().joint_names
    recordings: dict[str, Recording] = {}
    run_of: dict[tuple[str, str], int] = {}
    for reach in reaches:
        if reach.recording not in recordings:
            recordings = {reach.recording: read_recording(root / reach.recording)}  # one at a time
        key = (reach.participant, reach.session)
        run_of[key] = run_of.get(key, 0) + 1
        _write_run(out, reach, run_of[key], recordings[reach.recording], joints)
    _write_top(out, root, authors or [], license_)
    return {
        "participants": len({r.participant for r in reaches}),
        "sessions": len(run_of),
        "runs": len(reaches),
    }


def _clear(out: Path) -> None:
    """Make ``out`` an empty folder: never delete a folder that is not an earlier export
    of ours (a mistyped ``--out ~`` must cost nothing)."""
    if out.exists() and any(out.iterdir()):
        description = out / "dataset_description.json"
        try:
            ours = json.loads(description.read_text())["GeneratedBy"][0]["Name"] == "dammrl"
        except (OSError, ValueError, KeyError, IndexError, TypeError):
            ours = False
        if not ours:
            raise CatalogueError(
                f"{out} is not empty and is no BIDS export of dammrl's: give a new folder"
            )
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)


def _reaches(root: Path) -> Iterator[Reach]:
    names, rows = query(
        root,
        "SELECT participant, session, trial, attempt, block, recording, "
        "episode, start_ns, end_ns FROM trials ORDER BY participant, session, "
        "start_ns",
    )
    for row in rows:
        yield Reach(**dict(zip(names, row, strict=True)))


# ---- one run ---------------------------------------------------------------------------


def _stem(reach: Reach) -> str:
    return f"sub-{reach.participant}_ses-{_label(reach.session)}_task-{TASK}"


def _label(session: str) -> str:
    return session.removeprefix("ses-")


def _write_run(
    out: Path, reach: Reach, run: int, recording: Recording, joints: tuple[str, ...]
) -> None:
    messages = [(t, m) for t, m in recording.decoded(*KEPT) if _in_reach(t, m, reach)]
    states = [(t, m) for t, m in messages if isinstance(m, RobotState)]
    if len(states) < 2:
        return
    clock = RobotClock(states)
    folder = out / f"sub-{reach.participant}" / f"ses-{_label(reach.session)}"
    stem = f"{_stem(reach)}_tracksys-{TRACKING_SYSTEM}_run-{run:02d}"
    _write_motion(folder / "motion", stem, states, clock, joints)
    _write_tsv(
        folder / "motion" / f"{stem}_events.tsv", EVENT_COLUMNS, _events(messages, clock, reach)
    )
    _write_physio(folder / "beh", f"{_stem(reach)}_run-{run:02d}", messages, clock)


KEPT = (
    RobotState,
    DecisionRequest,
    Intent,
    StepEvent,
    SessionControl,
    EpisodeResult,
    SensorSample,
    SignalChunk,
)


def _episode(message: Any) -> int | None:
    return getattr(message, "episode", None)


def _in_reach(log_ns: int, message: Any, reach: Reach) -> bool:
    """A message of the reach: tagged with its episode (a run numbers each once), or
    untagged and logged between its goal and its result. Tagged messages are not bound by
    the goal's log time: the recorder hears the goal and the arm's reset state on separate
    subscribers, in either order on a loaded machine."""
    episode = _episode(message)
    if episode is not None:
        return episode == reach.episode and log_ns <= reach.end_ns
    return reach.start_ns <= log_ns <= reach.end_ns


class RobotClock:
    """A reach's time: seconds from its first state on the robot's clock; receipt times
    (ns) mapped onto it between the states around them."""

    def __init__(self, states: list[tuple[int, RobotState]]) -> None:
        self.log_ns = np.array([t for t, _ in states], dtype=float)
        self.robot_s = np.array([s.t_s for _, s in states])
        self.t0 = float(self.robot_s[0])

    def of_robot(self, t_s: float) -> float:
        return round(t_s - self.t0, 6)

    def of_receipt(self, log_ns: int) -> float:
        return round(float(np.interp(log_ns, self.log_ns, self.robot_s)) - self.t0, 6)


def _write_motion(
    folder: Path,
    stem: str,
    states: list[tuple[int, RobotState]],
    clock: RobotClock,
    joints: tuple[str, ...],
) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rows = [[*s.ee_pos_m, *s.ee_vel_m_s, *s.q_rad] for _, s in states]
    with open(folder / f"{stem}_motion.tsv", "w", newline="") as f:  # no header: BIDS motion
        csv.writer(f, delimiter="\t", lineterminator="\n").writerows(
            [[f"{v:.6g}" for v in row] for row in rows]
        )
    channels = [(f"end_effector_{a}", "POS", a, "end_effector", "m") for a in AXES]
    channels += [(f"end_effector_v{a}", "VEL", a, "end_effector", "m/s") for a in AXES]
    channels += [(f"{joint}_angle", "JNTANG", "n/a", joint, "rad") for joint in joints]
    channels = [
        (name, component, kind, point, units)  # the order BIDS requires
        for name, kind, component, point, units in channels
    ]
    _write_tsv(
        folder / f"{stem}_channels.tsv",
        ("name", "component", "type", "tracked_point", "units"),
        channels,
    )
    duration = float(states[-1][1].t_s - states[0][1].t_s)
    rate = (len(states) - 1) / duration if duration > 0 else 0.0
    sidecar = {
        "TaskName": TASK,
        "TaskDescription": "Reach to a button on a table with a 6-DoF rehabilitation arm; "
        "the participant decides the primary axis (+1/-1) and the admission radius.",
        "SamplingFrequency": round(rate, 3),
        "SamplingFrequencyEffective": round(rate, 3),
        "TrackingSystemName": TRACKING_SYSTEM,
        "Manufacturer": "dammrl (the arm's own encoders and forward kinematics)",
        "SoftwareVersions": __version__,
        "RecordingDuration": round(duration, 3),
        "MotionChannelCount": len(channels),
        "POSChannelCount": 3,
        "VELChannelCount": 3,
        "JNTANGChannelCount": len(joints),
        "ORNTChannelCount": 0,
        "MISCChannelCount": 0,
        "MissingValues": "n/a",
        "SubjectArtefactDescription": "n/a",
        "TrackedPointsCount": 1 + len(joints),
        "SpatialAxes": "FLU",
        "RotationRule": "right-hand",
    }
    _write_json(folder / f"{stem}_motion.json", sidecar)


EVENT_COLUMNS = ("onset", "duration", "trial_type", "trial", "value", "detail")


def _events(
    messages: list[tuple[int, Any]], clock: RobotClock, reach: Reach
) -> list[tuple[Any, ...]]:
    rows: list[tuple[Any, ...]] = [
        (0.0, "n/a", "reach_start", reach.trial, reach.block, f"attempt {reach.attempt}")
    ]
    for log_ns, message in messages:
        row = _event(message, clock.of_receipt(log_ns), clock, reach.trial)
        if row is not None:
            rows.append(row)
    return sorted(rows, key=lambda r: float(r[0]))


def _event(message: Any, at_s: float, clock: RobotClock, trial: int) -> tuple[Any, ...] | None:
    if isinstance(message, DecisionRequest):
        return (
            clock.of_robot(message.t_s),
            "n/a",
            "decision_asked",
            trial,
            message.request,
            f"human model {message.human_model}",
        )
    if isinstance(message, Intent):
        detail = (
            f"radius {message.radius_m:.4f} m; source {message.source}; "
            f"confidence {message.confidence:.3f}; took {message.decision_s:.3f} s"
        )
        return (at_s, "n/a", "decision", trial, message.u_h, detail)
    if isinstance(message, StepEvent):
        return (
            clock.of_robot(message.t_s),
            "n/a",
            f"step_{message.trigger}",
            trial,
            message.index,
            f"radius {message.radius_m:.4f} m",
        )
    if isinstance(message, SessionControl):
        return (
            at_s,
            "n/a",
            f"therapist_{message.action}",
            trial,
            message.who,
            message.why or "n/a",
        )
    if isinstance(message, EpisodeResult):
        return (at_s, "n/a", "reach_end", trial, message.outcome, message.reason)
    return None


def _write_physio(
    folder: Path, stem: str, messages: list[tuple[int, Any]], clock: RobotClock
) -> None:
    pressure = [
        (clock.of_receipt(t), m.raw, m.level) for t, m in messages if isinstance(m, SensorSample)
    ]
    if pressure:
        _physio(
            folder,
            f"{stem}_recording-pressure",
            ["time", "raw_counts", "level"],
            [[t, raw, "n/a" if level is None else level] for t, raw, level in pressure],
            rate=_rate([p[0] for p in pressure]),
        )
    chunks = [m for _, m in messages if isinstance(m, SignalChunk)]
    if chunks:
        rows = [
            [clock.of_receipt(stamp), *sample]
            for chunk in chunks
            for stamp, sample in zip(chunk.stamps_ns, chunk.samples, strict=True)
        ]
        width = len(rows[0]) - 1 if rows else 0
        columns = ["time", *(f"ch{c + 1}" for c in range(width))]
        _physio(folder, f"{stem}_recording-wearable", columns, rows, rate=chunks[0].rate_hz)


def _rate(times: list[float]) -> float:
    return round((len(times) - 1) / (times[-1] - times[0]), 3) if times[-1] > times[0] else 1.0


def _physio(
    folder: Path, stem: str, columns: list[str], rows: list[list[Any]], rate: float
) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    text = io.StringIO(newline="")
    csv.writer(text, delimiter="\t", lineterminator="\n").writerows(
        [["n/a" if v is None else v for v in row] for row in rows]  # a lost sample
    )
    packed = gzip.compress(text.getvalue().encode(), mtime=0)  # no name, no time: as BIDS asks
    (folder / f"{stem}_physio.tsv.gz").write_bytes(packed)
    sidecar: dict[str, Any] = {
        "SamplingFrequency": rate,
        "StartTime": rows[0][0] if rows else 0.0,
        "Columns": columns,
    }
    sidecar |= {
        name: PHYSIO_COLUMNS.get(name)
        or {"Description": f"the wearable's channel {name[2:]}, as its stream sent it"}
        for name in columns
    }
    _write_json(folder / f"{stem}_physio.json", sidecar)


PHYSIO_COLUMNS = {
    "time": {"Description": "seconds from the reach's first state (robot clock)", "Units": "s"},
    "raw_counts": {"Description": "the pad's ADC counts, as it sent them"},
    "level": {
        "Description": "the filtered pressure normalised by the person's calibration: "
        "0 at rest, 1 a firm press"
    },
}
"""What the physio files' columns mean (a wearable's channels are described apart)."""


# ---- the dataset's own files ----------------------------------------------------------


EVENTS_SIDECAR = {
    "trial": {"Description": "the protocol's trial number in the session"},
    "value": {
        "Description": "reach_start: the block; decision_asked: the request number; "
        "decision: the command u_h (+1 forward, -1 back on the primary axis); step_*: "
        "the micro-step's index; therapist_*: who; reach_end: the outcome"
    },
    "detail": {
        "Description": "what goes with it (the radius, the decision's source and "
        "confidence, the reason)"
    },
    "trial_type": {
        "Description": "what happened",
        "Levels": {
            "reach_start": "the reach began (its first state)",
            "decision_asked": "the participant was asked to decide",
            "decision": "the participant's (or the therapist's) decision",
            "step_event": "a micro-step advanced by the event trigger",
            "step_fixed": "a micro-step advanced by the fixed-rate timer",
            "reach_end": "the reach ended (its outcome)",
        },
    },
    "StimulusPresentation": {"SoftwareName": "dammrl", "SoftwareVersion": __version__},
}
SESSIONS_SIDECAR = {
    "acq_time": {"Description": "the session's first recorded message (UTC)"},
    "protocol": {"Description": "the protocol's name"},
    "protocol_version": {"Description": "the protocol's version"},
    "protocol_sha256": {"Description": "SHA-256 of the protocol's canonical form"},
}


def _write_top(out: Path, root: Path, authors: list[str], license_: str | None) -> None:
    description: dict[str, Any] = {
        "Name": "dammrl sessions",
        "BIDSVersion": BIDS_VERSION,
        "DatasetType": "raw",
        "GeneratedBy": [
            {
                "Name": "dammrl",
                "Version": __version__,
                "Description": "dammrl session bids, from the session recordings",
            }
        ],
    }
    if authors:
        description["Authors"] = authors
    if license_:
        description["License"] = license_
    _write_json(out / "dataset_description.json", description)
    _write_json(out / f"task-{TASK}_events.json", EVENTS_SIDECAR)
    _write_json(out / "sessions.json", SESSIONS_SIDECAR)
    (out / "README").write_text(
        "Reaches with the dammrl rehabilitation arm (event-triggered human-robot "
        "co-adaptation), exported from the session recordings by `dammrl session bids`.\n"
        "One run per reach: the arm's kinematics (motion), the decisions, steps and the "
        "therapist's acts (events), the person's raw input where recorded (beh, physio).\n"
    )
    _, rows = query(root, "SELECT participant FROM participants ORDER BY participant")
    _write_tsv(out / "participants.tsv", ("participant_id",), [(f"sub-{r[0]}",) for r in rows])
    _write_json(
        out / "participants.json",
        {
            "participant_id": {
                "Description": "pseudonymous id given at enrolment (dammrl stores no names)"
            }
        },
    )
    _, sessions = query(
        root,
        "SELECT participant, session, strftime(started, "
        "'%Y-%m-%dT%H:%M:%S'), protocol, protocol_version, protocol_sha256 "
        "FROM sessions ORDER BY participant, session",
    )
    for participant, session, started, *protocol in sessions:
        _write_tsv(
            out / f"sub-{participant}" / f"sub-{participant}_sessions.tsv",
            ("session_id", "acq_time", "protocol", "protocol_version", "protocol_sha256"),
            [(f"ses-{_label(session)}", started, *protocol)],
            append=True,
        )


def _write_tsv(
    path: Path,
    columns: tuple[str, ...],
    rows: list[tuple[Any, ...]] | list[list[Any]],
    append: bool = False,
) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    new = not (append and path.exists())
    with open(path, "w" if new else "a", newline="") as f:
        writer = csv.writer(f, delimiter="\t", lineterminator="\n")
        if new:
            writer.writerow(columns)
        writer.writerows([[_cell(v) for v in row] for row in rows])


def _cell(value: Any) -> Any:
    """A TSV cell: n/a for nothing; free text (a therapist's reason) on one line without
    tabs, as TSV has no quoting."""
    if value is None:
        return "n/a"
    return " ".join(value.split()) or "n/a" if isinstance(value, str) else value


def _write_json(path: Path, content: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content, indent=2) + "\n")
