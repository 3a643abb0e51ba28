"""One BIDS run per reach: the arm's kinematics (motion), what happened (events) and the
person's raw input (beh/physio), all on the robot's clock.

A stack run's recordings are read once, every message the export keeps decoded once,
and each of the run's reaches takes its own: the messages tagged with its episode, and
the untagged ones logged between its goal and its result.
"""

from __future__ import annotations

import bisect
import csv
import gzip
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dammrl import __version__
from dammrl.data.bids.dataset import TASK, TRACKING_SYSTEM, label, write_json, write_tsv
from dammrl.stack.recording import read_recording
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

AXES = ("x", "y", "z")
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


def reach_stem(reach: Reach) -> str:
    return f"sub-{reach.participant}_ses-{label(reach.session)}_task-{TASK}"


@dataclass
class RunMessages:
    """A stack run's kept messages, decoded once: tagged ones by episode, the others in
    receipt order."""

    tagged: dict[int, list[tuple[int, Any]]] = field(default_factory=dict)
    untagged: list[tuple[int, Any]] = field(default_factory=list)

    @classmethod
    def read(cls, files: list[Path]) -> RunMessages:
        """The messages of ``files`` (a run's part and its continuations, in order)."""
        found = cls()
        for path in files:
            for log_ns, message in read_recording(path).decoded(*KEPT):
                episode = getattr(message, "episode", None)
                if episode is None:
                    found.untagged.append((log_ns, message))
                else:
                    found.tagged.setdefault(episode, []).append((log_ns, message))
        found.untagged.sort(key=lambda m: m[0])
        return found

    def of(self, reach: Reach) -> list[tuple[int, Any]]:
        """The reach's messages in receipt order. Tagged messages are not bound by the
        goal's log time: the recorder hears the goal and the arm's reset state on separate
        subscribers, in either order on a loaded machine."""
        tagged = [(t, m) for t, m in self.tagged.get(reach.episode, []) if t <= reach.end_ns]
        times = [t for t, _ in self.untagged]
        first = bisect.bisect_left(times, reach.start_ns)
        last = bisect.bisect_right(times, reach.end_ns)
        return sorted(tagged + self.untagged[first:last], key=lambda m: m[0])


def write_run(out: Path, reach: Reach, run: int, messages: list[tuple[int, Any]],
              joints: tuple[str, ...]) -> bool:  # fmt: skip
    """The reach's files under ``out``; False when it has too few states for a run."""
    states = [(t, m) for t, m in messages if isinstance(m, RobotState)]
    if len(states) < 2:
        return False
    clock = RobotClock(states)
    folder = out / f"sub-{reach.participant}" / f"ses-{label(reach.session)}"
    name = f"{reach_stem(reach)}_tracksys-{TRACKING_SYSTEM}_run-{run:02d}"
    _write_motion(folder / "motion", name, states, clock, joints)
    write_tsv(folder / "motion" / f"{name}_events.tsv", EVENT_COLUMNS,
              events(messages, clock, reach))  # fmt: skip
    _write_physio(folder / "beh", f"{reach_stem(reach)}_run-{run:02d}", messages, clock)
    return True


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
    write_tsv(
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
    write_json(folder / f"{stem}_motion.json", sidecar)


EVENT_COLUMNS = ("onset", "duration", "trial_type", "trial", "value", "detail")


def events(
    messages: list[tuple[int, Any]], clock: RobotClock, reach: Reach
) -> list[tuple[Any, ...]]:
    """The reach's events, in time order on the robot's clock."""
    asked = {m.request: m for _, m in messages if isinstance(m, DecisionRequest)}
    rows: list[tuple[Any, ...]] = [
        (0.0, "n/a", "reach_start", reach.trial, reach.block, f"attempt {reach.attempt}")
    ]
    for log_ns, message in messages:
        row = _event(message, clock.of_receipt(log_ns), clock, reach.trial, asked)
        if row is not None:
            rows.append(row)
    return sorted(rows, key=lambda r: float(r[0]))


def _event(message: Any, at_s: float, clock: RobotClock, trial: int,
           asked: dict[int, DecisionRequest]) -> tuple[Any, ...] | None:  # fmt: skip
    if isinstance(message, DecisionRequest):
        return (clock.of_robot(message.t_s), "n/a", "decision_asked", trial, message.request,
                f"human model {message.human_model}")  # fmt: skip
    if isinstance(message, Intent):
        return _decision(message, at_s, clock, trial, asked.get(message.request))
    if isinstance(message, StepEvent):
        return (clock.of_robot(message.t_s), "n/a", f"step_{message.trigger}", trial,
                message.index, f"radius {message.radius_m:.4f} m")  # fmt: skip
    if isinstance(message, SessionControl):
        return (at_s, "n/a", f"therapist_{message.action}", trial, message.who,
                message.why or "n/a")  # fmt: skip
    if isinstance(message, EpisodeResult):
        return (at_s, "n/a", "reach_end", trial, message.outcome, message.reason)
    return None


def _decision(intent: Intent, at_s: float, clock: RobotClock, trial: int,
              request: DecisionRequest | None) -> tuple[Any, ...]:  # fmt: skip
    """A decision on the robot's clock: its request's time plus the time it took (when
    the controller applies it); unasked, or its request unrecorded, at its receipt."""
    detail = (f"radius {intent.radius_m:.4f} m; source {intent.source}; "
              f"confidence {intent.confidence:.3f}; took {intent.decision_s:.3f} s")  # fmt: skip
    if request is None:
        return (at_s, "n/a", "decision", trial, intent.u_h, f"{detail}; at its receipt")
    onset = clock.of_robot(request.t_s + intent.decision_s)
    return (onset, "n/a", "decision", trial, intent.u_h, detail)


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
    write_json(folder / f"{stem}_physio.json", sidecar)


PHYSIO_COLUMNS = {
    "time": {"Description": "seconds from the reach's first state (robot clock)", "Units": "s"},
    "raw_counts": {"Description": "the pad's ADC counts, as it sent them"},
    "level": {
        "Description": "the filtered pressure normalised by the person's calibration: "
        "0 at rest, 1 a firm press"
    },
}
"""What the physio files' columns mean (a wearable's channels are described apart)."""
