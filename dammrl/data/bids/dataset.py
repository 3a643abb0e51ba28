"""The dataset's own files (description, participants, sessions, the events' meaning)
and how every file is written (TSV as BIDS has it, JSON)."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from dammrl import __version__
from dammrl.data.catalogue import query

BIDS_VERSION = "1.11.0"
TASK = "reach"
TRACKING_SYSTEM = "dammrl"


def label(session: str) -> str:
    """A session's BIDS label (``ses-01`` -> ``01``)."""
    return session.removeprefix("ses-")


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
            "decision": "the participant's (or the therapist's) decision, when the "
            "controller took it: its request's time plus the time the decision took",
            "step_event": "a micro-step advanced by the event trigger",
            "step_fixed": "a micro-step advanced by the fixed-rate timer",
            "reach_end": "the reach ended (its outcome)",
            "therapist_pause": "the therapist paused the reach (the arm holds)",
            "therapist_resume": "the therapist resumed it",
            "therapist_skip": "the therapist ended the reach: the trial counts as skipped",
            "therapist_again": "the therapist ended the reach: the trial runs again",
            "therapist_end-block": "the therapist ended the reach and the rest of its block",
            "therapist_take": "the therapist took the decisions over",
            "therapist_decide": "the therapist decided for the participant",
            "therapist_give": "the therapist gave the decisions back",
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


def write_top(out: Path, root: Path, authors: list[str], license_: str | None) -> None:
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
    write_json(out / "dataset_description.json", description)
    write_json(out / f"task-{TASK}_events.json", EVENTS_SIDECAR)
    write_json(out / "sessions.json", SESSIONS_SIDECAR)
    (out / "README").write_text(
        "Reaches with the dammrl rehabilitation arm (event-triggered human-robot "
        "co-adaptation), exported from the session recordings by `dammrl session bids`.\n"
        "One run per reach: the arm's kinematics (motion), the decisions, steps and the "
        "therapist's acts (events), the person's raw input where recorded (beh, physio).\n"
    )
    # the sessions with a reach recorded (a session known only from its trial log has none)
    _, rows = query(root, "SELECT DISTINCT participant FROM sessions WHERE trials > 0 "
                          "ORDER BY participant")  # fmt: skip
    write_tsv(out / "participants.tsv", ("participant_id",), [(f"sub-{r[0]}",) for r in rows])
    write_json(
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
        "FROM sessions WHERE trials > 0 ORDER BY participant, session",
    )
    for participant, session, started, *protocol in sessions:
        write_tsv(
            out / f"sub-{participant}" / f"sub-{participant}_sessions.tsv",
            ("session_id", "acq_time", "protocol", "protocol_version", "protocol_sha256"),
            [(f"ses-{label(session)}", started, *protocol)],
            append=True,
        )


def write_tsv(
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


def write_json(path: Path, content: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content, indent=2) + "\n")
