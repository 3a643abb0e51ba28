"""A BIDS re-export keeps the lab's work, and decisions sit on the robot's clock."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from dammrl.cli import main
from dammrl.data.bids import export
from dammrl.data.catalogue import CatalogueError, build
from schemas import DecisionRequest, Intent
from tests.test_catalogue import MS, _study, write_run
from tests.test_schemas import EXAMPLES

REQUEST = next(m for m in EXAMPLES if isinstance(m, DecisionRequest))
INTENT = next(m for m in EXAMPLES if isinstance(m, Intent))


@pytest.fixture
def exported(tmp_path: Path) -> tuple[Path, Path]:
    root = tmp_path / "sessions"
    for session, t0 in (("ses-01", 10_000), ("ses-02", 90_000)):
        write_run(root / "P007" / session / "recordings" / "part-01.mcap",
                  _study("b", [1, 2], session), [(1, 5.0), (2, 6.0)], t0 * MS)  # fmt: skip
    build(root)
    out = tmp_path / "bids"
    export(root, out)
    return root, out


def _lab_work(out: Path) -> dict[str, str]:
    work = {
        "derivatives/kinematics/sub-P007/features.tsv": "a\tb\n1\t2\n",
        "code/analysis.py": "print('the lab')\n",
        "sourcedata/notes.txt": "session notes\n",
        "CHANGES": "1.0.1 2026-11-26\n  - the lab's fix\n",
        "sub-P007/ses-01/scans_note.txt": "a file inside a subject folder\n",
    }
    for rel, text in work.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(text)
    return work


def test_a_re_export_keeps_what_the_lab_added_and_says_so(
    exported: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    root, out = exported
    work = _lab_work(out)
    assert main(["sessions", "bids", "--root", str(root), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert all((out / rel).read_text() == text for rel, text in work.items())
    assert "kept what the lab added: CHANGES, code/ (1 file), derivatives/ (1 file), " in err
    assert "sourcedata/ (1 file), sub-P007/ (1 file)" in err
    assert len(list(out.glob("sub-P007/ses-0*/motion/*_motion.tsv"))) == 4


def test_files_dammrl_no_longer_writes_go_and_nothing_of_the_labs_does(
    exported: tuple[Path, Path],
) -> None:
    root, out = exported
    work = _lab_work(out)
    (root / "P007" / "ses-02" / "recordings" / "part-01.mcap").unlink()  # a session withdrawn
    build(root)
    export(root, out)
    assert not (out / "sub-P007" / "ses-02").exists()
    assert all((out / rel).read_text() == text for rel, text in work.items())


def test_the_labs_columns_and_keys_are_merged_and_other_edits_kept(
    exported: tuple[Path, Path],
) -> None:
    root, out = exported
    (out / "participants.tsv").write_text("participant_id\tage\tgroup\nsub-P007\t61\tstroke\n"
                                          "sub-P099\t70\texcluded\n")  # fmt: skip
    description = json.loads((out / "dataset_description.json").read_text())
    description |= {"Funding": ["a grant"], "Name": "the lab's name", "BIDSVersion": "1.0.0"}
    (out / "dataset_description.json").write_text(json.dumps(description))
    events = next(out.glob("sub-P007/ses-01/motion/*_run-01_events.tsv"))
    events.write_text(events.read_text() + "9.0\tn/a\tlab_note\t1\tn/a\tthe lab's\n")
    write_run(root / "P008" / "ses-01" / "recordings" / "part-01.mcap",
              _study("b", [1]) | {"participant": "P008"}, [(1, 4.0)], 200_000 * MS)  # fmt: skip
    build(root)
    kept = export(root, out, authors=["A. B"]).kept
    text = (out / "participants.tsv").read_text()
    rows = list(csv.DictReader(text.splitlines(), delimiter="\t"))
    assert [(r["participant_id"], r["age"], r["group"]) for r in rows] == [
        ("sub-P007", "61", "stroke"), ("sub-P008", "n/a", "n/a"), ("sub-P099", "70", "excluded")
    ]  # fmt: skip
    merged = json.loads((out / "dataset_description.json").read_text())
    assert merged["Funding"] == ["a grant"] and merged["Name"] == "the lab's name"
    assert merged["BIDSVersion"] == "1.11.0" and merged["Authors"] == ["A. B"]
    assert events.read_text().endswith("the lab's\n")
    assert kept.merged == ["dataset_description.json", "participants.tsv"]
    assert kept.as_left == [events.relative_to(out).as_posix()]
    export(root, out)  # the next time too: the lab's still
    assert "age" in (out / "participants.tsv").read_text()


def test_a_folder_of_others_is_refused_and_an_export_before_the_list_kept_file_by_file(
    exported: tuple[Path, Path], tmp_path: Path
) -> None:
    root, out = exported
    other = tmp_path / "thesis"
    other.mkdir()
    (other / "chapter1.tex").write_text("precious")
    with pytest.raises(CatalogueError, match="not empty"):
        export(root, other)
    assert [p.name for p in other.iterdir()] == ["chapter1.tex"]
    (out / ".dammrl" / "export.json").unlink()  # as dammrl exported before the list
    _lab_work(out)
    export(root, out)
    assert (out / "code" / "analysis.py").is_file() and (out / ".dammrl" / "export.json").is_file()


def test_a_decision_sits_at_its_request_plus_the_time_it_took_on_the_robots_clock(
    tmp_path: Path,
) -> None:
    """In lockstep the robot's clock waits while the simulated person decides, so the
    decision arrives 1 ms after its request by the receipt times; the controller applies
    it 0.4 s later on the robot's clock, as its detail says."""
    request = REQUEST.model_copy(update={"episode": 1, "request": 3, "t_s": 1.0})
    intent = INTENT.model_copy(update={"episode": 1, "request": 3, "decision_s": 0.4})
    unasked = INTENT.model_copy(update={"episode": 1, "request": -1, "decision_s": 0.1})
    root = tmp_path / "sessions"
    write_run(root / "P007" / "ses-01" / "recordings" / "part-01.mcap", _study("b", [1]),
              [(1, 5.0)], 10_000 * MS, during=[request, intent, unasked])  # fmt: skip
    build(root)
    export(root, tmp_path / "bids")
    events = next((tmp_path / "bids").rglob("*_events.tsv")).read_text().splitlines()
    rows = [line.split("\t") for line in events[1:]]
    asked = [float(r[0]) for r in rows if r[2] == "decision_asked"]
    answered = [float(r[0]) for r in rows if r[2] == "decision" and "receipt" not in r[5]]
    assert asked == [1.0] and answered == [1.4]  # the reach's first state: robot time 0
    assert len([r for r in rows if r[5].endswith("took 0.100 s; at its receipt")]) == 1
