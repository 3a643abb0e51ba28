"""A catalogue no query can harm: no file access from a query, builds that never leave a
half-written catalogue, concurrent builds and queries that serialise, and a damaged
catalogue that is one line and a rebuild, never a traceback."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

import dammrl.data.catalogue.store as store
from dammrl.cli import main
from dammrl.data.catalogue import CatalogueError, build, catalogue_path, query, stale
from tests.test_catalogue import MS, _study, dump_catalogue, write_run

RECORDING = Path("P007") / "ses-01" / "recordings" / "part-01.mcap"


@pytest.fixture
def root(tmp_path: Path) -> Path:
    write_run(tmp_path / RECORDING, _study("b", [1, 2]), [(1, 5.0), (2, 6.0)], 10_000 * MS)
    write_run(tmp_path / "P008" / "ses-01" / "recordings" / "part-01.mcap",
              _study("b", [1]) | {"participant": "P008"}, [(1, 4.0)], 20_000 * MS)  # fmt: skip
    build(tmp_path)
    return tmp_path


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize(
    "sql",
    [
        "COPY (SELECT 'gone' AS x) TO '{target}' (FORMAT CSV)",
        "COPY trials TO '{target}' (FORMAT PARQUET)",
        "SELECT 1; COPY (SELECT 1) TO '{target}'",
        "EXPORT DATABASE '{folder}'",
        "ATTACH '{target}.duckdb' AS other",
        "SELECT * FROM read_csv('{target}')",
        "SET enable_external_access = true",
        "INSTALL httpfs",
        "DROP TABLE trials",
    ],
)
def test_no_query_can_touch_a_file(root: Path, sql: str) -> None:
    target = root / RECORDING
    before, files = _sha(target), sorted(p for p in root.rglob("*") if p.is_file())
    with pytest.raises(CatalogueError, match="query refused"):
        query(root, sql.format(target=target, folder=root / "P007" / "exported"))
    assert _sha(target) == before
    assert sorted(p for p in root.rglob("*") if p.is_file()) == files
    assert query(root, "SELECT count(*) FROM trials")[1] == [(3,)]


def test_copy_to_a_recording_from_the_command_line_is_one_line_and_changes_nothing(
    root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = root / RECORDING
    before = _sha(target)
    sql = f"COPY (SELECT 'gone' AS x) TO '{target}' (FORMAT CSV)"
    assert main(["sessions", "query", "--root", str(root), sql]) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "file system operations are disabled" in err
    assert _sha(target) == before
    assert main(["sessions", "catalogue", "--root", str(root)]) == 0
    assert "3 trials" in capsys.readouterr().out  # the next build drops nothing


@pytest.mark.parametrize("step", ["_fill", "_swap"])
def test_a_build_that_fails_midway_leaves_a_whole_catalogue(
    root: Path, monkeypatch: pytest.MonkeyPatch, step: str
) -> None:
    """Before the rename the last catalogue stays (stale: a recording came since); after
    it the new one is whole; nothing of the build is left behind either way."""
    first = dump_catalogue(root)
    write_run(root / "P007" / "ses-02" / "recordings" / "part-01.mcap",
              _study("b", [1], "ses-02"), [(1, 7.0)], 90_000 * MS)  # fmt: skip

    def dies(*_: object) -> None:
        raise OSError("the disk is full")

    monkeypatch.setattr(store, step, dies)
    with pytest.raises(OSError, match="disk is full"):
        build(root)
    if step == "_fill":
        assert dump_catalogue(root) == first and stale(root) is not None
    else:
        assert len(dump_catalogue(root)["trials"]) == len(first["trials"]) + 1
        assert stale(root) is None
    assert not list((root / "catalogue").glob(".build-*"))


def test_a_crashed_builds_leftovers_never_count(root: Path) -> None:
    (root / "catalogue" / ".build-999-dead").mkdir()
    ((root / "catalogue" / ".build-999-dead") / "catalogue.duckdb").write_bytes(b"half")
    build(root)
    assert not list((root / "catalogue").glob(".build-*"))


@pytest.mark.parametrize("damage", ["bit flip", "random bytes", "empty", "cut in half"])
def test_a_damaged_catalogue_is_one_line_and_a_rebuild(
    root: Path, damage: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = catalogue_path(root)
    data = bytearray(path.read_bytes())
    if damage == "bit flip":
        for offset in range(100, len(data) - 4096, 4096):  # in the header and every block
            data[offset] ^= 0xFF
    elif damage == "random bytes":
        data = bytearray(os.urandom(len(data)))
    elif damage == "empty":
        data = bytearray()
    else:
        data = data[: len(data) // 2]
    path.write_bytes(bytes(data))
    capsys.readouterr()
    assert main(["sessions", "query", "--root", str(root), "SELECT count(*) AS n FROM trials"]) == 0
    out, err = capsys.readouterr()
    assert out.split() == ["n", "-", "3"] or out.split()[-1] == "3"
    (said,) = [line for line in err.splitlines() if "rebuilding it" in line]
    assert "unreadable" in said and "Traceback" not in err
    assert stale(root) is None


def test_a_catalogue_of_an_older_layout_is_rebuilt(root: Path) -> None:
    import duckdb

    path = catalogue_path(root)
    path.unlink()
    with duckdb.connect(str(path)) as db:  # as dammrl built it before: no about, no sources
        db.execute("CREATE TABLE trials (participant VARCHAR)")
    assert stale(root) == "the catalogue is of an older layout"


def test_a_changed_deleted_or_added_source_makes_the_catalogue_stale(root: Path) -> None:
    assert stale(root) is None
    log = root / "P007" / "ses-01" / "trials.jsonl"
    log.write_text('{"trial": 1}\n')
    assert stale(root) == "the catalogue is older than the recordings"
    build(root)
    (root / "P008" / "ses-01" / "recordings" / "part-01.mcap").unlink()
    assert stale(root) == "the catalogue is older than the recordings"


@pytest.mark.slow
def test_ten_concurrent_builds_and_queries_leave_no_traceback_and_a_readable_catalogue(
    root: Path,
) -> None:
    """As stations sharing a folder do: five rebuild it, five ask it (every query finds
    it stale first: a new recording), at once."""
    write_run(root / "P007" / "ses-02" / "recordings" / "part-01.mcap",
              _study("b", [1], "ses-02"), [(1, 7.0)], 90_000 * MS)  # fmt: skip
    asking = [["sessions", "query", "SELECT count(*) FROM trials"], ["sessions", "trials"]]
    report = ["sessions", "report", "--all", "--out", str(root / "reports")]
    commands = [["sessions", "catalogue"]] * 5 + asking * 2 + [report]
    children = [
        subprocess.Popen([sys.executable, "-m", "dammrl", *c, "--root", str(root)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         stdin=subprocess.DEVNULL)
        for c in commands
    ]  # fmt: skip
    outcomes = [child.communicate(timeout=600) for child in children]
    for child, (_, err) in zip(children, outcomes, strict=True):
        assert child.returncode == 0 and "Traceback" not in err, err[-2000:]
        assert err.count("waiting for another build") <= 1
    assert stale(root) is None
    assert query(root, "SELECT count(*) FROM trials")[1] == [(4,)]
    answers = [out for (out, _), c in zip(outcomes, commands, strict=True) if c[1] == "query"]
    assert all(out.split()[-1] == "4" for out in answers)
