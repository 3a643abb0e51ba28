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
the reach's first state (robot clock). A decision is placed where the controller took
it: its request's robot time plus the time it took; a message without a robot time of
its own (a therapist's act, the result) by its receipt time, interpolated between the
states around it.

Exporting again into the same folder replaces only what dammrl wrote and keeps the
lab's work (``keeping``). The modules: ``dataset`` (the dataset's own files, how files
are written), ``runs`` (one run per reach), ``keeping``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dammrl.data.bids.dataset import write_top
from dammrl.data.bids.keeping import Kept, previous_files, put_in_place, staging
from dammrl.data.bids.runs import Reach, RunMessages, write_run
from dammrl.data.catalogue import query
from dammrl_core.robot import RobotSettings


@dataclass(frozen=True)
class Exported:
    """What an export wrote, and what it kept of the lab's."""

    participants: int
    sessions: int
    runs: int
    without_motion: int  # reaches with fewer than two of the arm's states: no run
    kept: Kept

    def counts(self) -> dict[str, int]:
        return {"participants": self.participants, "sessions": self.sessions, "runs": self.runs}


def export(
    root: Path, out: Path, authors: list[str] | None = None, license_: str | None = None
) -> Exported:
    """Write the BIDS dataset of every session in the catalogue under ``root`` to ``out``
    (what an earlier export wrote is replaced, the lab's work kept; the dataset's
    ``Authors`` and ``License`` as given)."""
    previous = previous_files(out)  # a folder neither empty nor ours is refused here
    out.mkdir(parents=True, exist_ok=True)
    staged = staging(out)
    reaches = _reaches(root)
    files = _run_files(root)
    joints = RobotSettings().load().joint_names
    numbered: dict[tuple[str, str], int] = {}
    written, read, messages = 0, "", RunMessages()
    for reach in reaches:
        if read != (run := _run_of(reach)):  # a run's reaches come together: read it once
            read, messages = run, RunMessages.read(files.get(run, [root / reach.recording]))
        key = (reach.participant, reach.session)
        numbered[key] = numbered.get(key, 0) + 1
        written += write_run(staged, reach, numbered[key], messages.of(reach), joints)
    write_top(staged, root, authors or [], license_)
    kept = put_in_place(out, staged, previous, bool(authors) or license_ is not None)
    return Exported(len({r.participant for r in reaches}), len(numbered), written,
                    len(reaches) - written, kept)  # fmt: skip


def _reaches(root: Path) -> list[Reach]:
    names, rows = query(
        root,
        "SELECT participant, session, trial, attempt, block, recording, "
        "episode, start_ns, end_ns FROM trials ORDER BY participant, session, start_ns",
    )
    return [Reach(**dict(zip(names, row, strict=True))) for row in rows]


def _run_of(reach: Reach) -> str:
    """A reach's run: its recording's part (``.../part-02-001.mcap`` -> ``.../part-02``)."""
    folder, _, name = reach.recording.rpartition("/")
    return f"{folder}/{name[: len('part-NN')]}"


def _run_files(root: Path) -> dict[str, list[Path]]:
    """The files the catalogue used of each run, in the order they were written."""
    _, rows = query(root, "SELECT recording FROM recordings WHERE used")
    files: dict[str, list[Path]] = {}
    for (recording,) in sorted(rows, key=lambda r: (len(r[0]), r[0])):  # the part first
        folder, _, name = recording.rpartition("/")
        files.setdefault(f"{folder}/{name[: len('part-NN')]}", []).append(root / recording)
    return files


__all__ = ["Exported", "Kept", "export"]
