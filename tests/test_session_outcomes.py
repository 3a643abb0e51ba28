"""From sessions to outcomes, as a lab runs it: two sessions of one simulated participant
through `dammrl session run` (the shipped protocol's blocks and targets, shorter: 3
trials a block, no rests), then the catalogue rebuilt from the recordings alone, both
reports, and a BIDS export that the official validator accepts without an error."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from dammrl.catalogue import query
from tests.busutil import free_port
from tests.test_catalogue import VALIDATOR, dump_catalogue

pytestmark = pytest.mark.slow
SHIPPED = Path(__file__).resolve().parents[1] / "dammrl" / "protocols" / "event-vs-fixed.yaml"


def _protocol(tmp_path: Path) -> Path:
    protocol = yaml.safe_load(SHIPPED.read_text())
    for block in protocol["blocks"]:
        block["trials"] = 1 if block.get("practice") else 3
        block.pop("rest_s", None)
    path = tmp_path / "protocol.yaml"
    path.write_text(yaml.safe_dump(protocol))
    return path


def _dammrl(*args: str) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(
        [sys.executable, "-m", "dammrl", *args],
        capture_output=True,
        text=True,
        timeout=600,
        stdin=subprocess.DEVNULL,
    )
    assert done.returncode == 0, done.stderr[-3000:]
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
    assert "1 participants, 2 sessions, 14 trials" in built.stdout

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
