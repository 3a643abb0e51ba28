"""From sessions to outcomes, as a lab runs it: two sessions of one simulated participant
through `dammrl session run` (the shipped protocol's blocks and targets, shorter: 3
trials a block, no rests), then the catalogue rebuilt from the recordings alone, both
reports, and a BIDS export that the official validator accepts without an error.

Then what must never happen to them: every reach confirmed on disk by the recorder and
every line of the trial logs found whole in the recordings; a query that would overwrite
a recording refused; a recording's cut tail reported as the trial it lost; a re-export
keeping the lab's derivatives; decisions placed on the robot's clock."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from dammrl.data.catalogue import query
from tests.busutil import free_port
from tests.test_catalogue import VALIDATOR, dump_catalogue

pytestmark = pytest.mark.slow
SHIPPED = (
    Path(__file__).resolve().parents[1] / "dammrl" / "people" / "protocols" / "event-vs-fixed.yaml"
)


def _protocol(tmp_path: Path) -> Path:
    protocol = yaml.safe_load(SHIPPED.read_text())
    for block in protocol["blocks"]:
        block["trials"] = 1 if block.get("practice") else 3
        block.pop("rest_s", None)
    path = tmp_path / "protocol.yaml"
    path.write_text(yaml.safe_dump(protocol))
    return path


def _dammrl(*args: str, ok: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(
        [sys.executable, "-m", "dammrl", *args],
        capture_output=True,
        text=True,
        timeout=600,
        stdin=subprocess.DEVNULL,
    )
    assert done.returncode == 0 or not ok, done.stderr[-3000:]
    return done


def test_two_sessions_give_a_catalogue_reports_and_valid_bids(tmp_path: Path) -> None:
    root, protocol = tmp_path / "sessions", _protocol(tmp_path)
    for _ in range(2):
        _dammrl(
            "session",
            "run",
            "--participant",
            "P001",
            "--protocol",
            str(protocol),
            "--root",
            str(root),
            "--lockstep",
            "--no-display",
            "--bus-port",
            str(free_port()),
        )
    built = _dammrl("sessions", "catalogue", "--root", str(root))
    assert "1 participant, 2 sessions, 14 trials" in built.stdout
    # every trial logged is recorded: whole, or short of a few of the arm's states that the
    # bus dropped on a loaded machine (the recorder's own gap count says the same)
    assert "data completeness: 14 reaches in the trial logs, " in built.stdout
    assert ", 0 missing from the recordings" in built.stdout
    for line in built.stderr.splitlines():
        assert re.fullmatch(r"P001/ses-0[12] trial \d: recorded in part: \d+ of its \d+ arm "
                            r"states missing inside it", line), line  # fmt: skip
    for session in ("ses-01", "ses-02"):  # the recorder confirmed each before its stack stopped
        events = (root / "P001" / session / "events.jsonl").read_text().splitlines()
        recorded = [e for e in map(json.loads, events) if e["what"] == "recorded"]
        confirmed = [t for e in recorded for t in [*e["confirmed"], *map(int, e["partial"])]]
        assert sorted(confirmed) == list(range(1, 8))
        assert all(e["unconfirmed"] == [] for e in recorded)

    # every trial the sessions logged is in the catalogue, with the same result
    for session in ("ses-01", "ses-02"):
        logged = [
            json.loads(line)
            for line in (root / "P001" / session / "trials.jsonl").read_text().splitlines()
        ]
        _, rows = query(
            root,
            "SELECT trial, t_total_s, recording FROM trials WHERE final "
            "AND session = ? ORDER BY trial",
            [session],
        )
        assert rows == [
            (e["trial"], e["result"]["t_total_s"], f"P001/{session}/{e['recording']}")
            for e in logged
        ]

    first = dump_catalogue(root)
    shutil.rmtree(root / "catalogue")
    _dammrl("sessions", "catalogue", "--root", str(root))
    assert dump_catalogue(root) == first

    listed = _dammrl("sessions", "trials", "--root", str(root), "--condition", "fixed", "--json")
    assert len(listed.stdout.splitlines()) == 6  # the fixed block, twice

    reports = tmp_path / "reports"
    _dammrl(
        "sessions", "report", "--participant", "P001", "--root", str(root), "--out", str(reports)
    )
    across = (reports / "P001.md").read_text()
    assert "| event | ses-01, ses-02 | 3 |" in across  # reliability over the repeated targets
    for name in ("P001.html", "P001_trends.png", "P001_ses-01.html", "P001_ses-02_blocks.png"):
        assert (reports / name).stat().st_size > 1000

    bids = tmp_path / "bids"
    _dammrl(
        "sessions",
        "bids",
        "--root",
        str(root),
        "--out",
        str(bids),
        "--author",
        "A. B",
        "--license",
        "CC0",
    )
    assert len(list(bids.glob("sub-P001/ses-0*/motion/*_motion.tsv"))) == 14
    validated = subprocess.run(
        [VALIDATOR, str(bids), "--format", "json", "--max-rows", "-1"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    issues = json.loads(validated.stdout)["issues"]["issues"]
    errors = [i for i in issues if i["severity"] == "error"]
    assert errors == [] and validated.returncode == 0, errors[:5]
    _decisions_on_the_robots_clock(bids)
    _nothing_is_lost(root, bids, tmp_path)


def _decisions_on_the_robots_clock(bids: Path) -> None:
    """Each decision comes the time it took after its request (lockstep: the receipt
    times put it a few ms after)."""
    after, took = [], []
    for events in bids.glob("sub-P001/ses-0*/motion/*_events.tsv"):
        asked_at = None
        for row in (line.split("\t") for line in events.read_text().splitlines()[1:]):
            if row[2] == "decision_asked":
                asked_at = float(row[0])
            elif row[2] == "decision" and asked_at is not None:
                after.append(float(row[0]) - asked_at)
                took.append(float(re.findall(r"took ([0-9.]+) s", row[5])[0]))
    assert len(after) > 20
    assert abs(statistics.median(after) - statistics.median(took)) < 0.011  # one control tick


def _nothing_is_lost(root: Path, bids: Path, tmp_path: Path) -> None:
    part = root / "P001" / "ses-02" / "recordings" / "part-02.mcap"
    before = hashlib.sha256(part.read_bytes()).hexdigest()
    copy = f"COPY (SELECT 'gone' AS x) TO '{part}' (FORMAT CSV)"
    refused = _dammrl("sessions", "query", "--root", str(root), copy, ok=False)
    assert refused.returncode != 0 and "disabled by configuration" in refused.stderr
    assert hashlib.sha256(part.read_bytes()).hexdigest() == before

    (bids / "derivatives" / "kinematics").mkdir(parents=True)
    (bids / "derivatives" / "kinematics" / "features.tsv").write_text("a\tb\n1\t2\n")
    again = _dammrl("sessions", "bids", "--root", str(root), "--out", str(bids))
    assert (bids / "derivatives" / "kinematics" / "features.tsv").read_text() == "a\tb\n1\t2\n"
    assert "kept what the lab added: derivatives/ (1 file)" in again.stderr

    part.write_bytes(part.read_bytes()[: part.stat().st_size * 2 // 3])  # its tail cut
    built = _dammrl("sessions", "catalogue", "--root", str(root))
    missing = [line for line in built.stderr.splitlines() if "missing from the recordings" in line]
    assert missing and all(line.startswith("P001/ses-02 trial ") for line in missing)
    assert all("part-02.mcap" in line and "cut at byte" in line for line in missing)
    report = tmp_path / "after-the-cut"
    _dammrl("sessions", "report", "--participant", "P001", "--root", str(root), "--session",
            "ses-02", "--out", str(report))  # fmt: skip
    text = (report / "P001_ses-02.md").read_text()
    assert f"**{len(missing)} missing from the recordings**" in text
