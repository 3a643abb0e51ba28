"""A re-export replaces what dammrl wrote and keeps the lab's work.

An export lists every file it wrote, with its SHA-256, in ``.dammrl/export.json`` (a
hidden folder: the BIDS validator ignores it). The next export into the same folder:

* replaces the files of that list the lab left as they were, and deletes those it no
  longer writes;
* keeps every other file (``derivatives/``, ``code/``, ``sourcedata/``, ``CHANGES``,
  anything): the lab's;
* keeps a listed file the lab changed, but merges into it what dammrl must say: the
  participants' new rows into ``participants.tsv`` (the lab's columns kept, ``n/a`` for
  a new participant), and into a JSON file dammrl's keys the lab did not set (the
  dataset's ``BIDSVersion`` and ``GeneratedBy`` always; ``Authors`` and ``License``
  when given now); any other changed file is kept as the lab left it, and said. A file
  is the lab's changed one when it differs from what dammrl last wrote there.

A folder that holds neither such a list nor a dataset dammrl generated, and is not
empty, is refused: a mistyped ``--out ~`` costs nothing. An export made before the list
existed is replaced file by file (``participants.tsv`` and JSON files merged); nothing
it does not write now is deleted.

The new files are written to ``.dammrl/staging`` first and moved into place only when all
are written; the list names the old and the new files while they move, so a crash
leaves nothing of dammrl's unlisted.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import shutil
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from dammrl import __version__
from dammrl.data.catalogue import CatalogueError

MANIFEST = Path(".dammrl") / "export.json"
STAGING = Path(".dammrl") / "staging"
DAMMRL_SETS = ("BIDSVersion", "GeneratedBy")
"""Keys of ``dataset_description.json`` that say what the export is: always dammrl's."""


@dataclass
class Kept:
    """What a re-export kept of the lab's, to be said."""

    added: list[str] = field(default_factory=list)  # files and folders dammrl never wrote
    merged: list[str] = field(default_factory=list)  # changed files, dammrl's part merged in
    as_left: list[str] = field(default_factory=list)  # changed files kept as the lab left them

    def lines(self) -> list[str]:
        said = []
        if self.added:
            said.append(f"kept what the lab added: {', '.join(self.added)}")
        if self.merged:
            said.append(f"kept the lab's changes, dammrl's rows and keys merged in: "
                        f"{', '.join(self.merged)}")  # fmt: skip
        if self.as_left:
            said.append(f"kept as the lab changed them (delete one to have dammrl write it "
                        f"again): {', '.join(self.as_left)}")  # fmt: skip
        return said


def previous_files(out: Path) -> dict[str, str] | None:
    """What the export in ``out`` wrote (path -> SHA-256); ``{}`` for an empty or new
    folder and for an export of dammrl's made before the list existed; a CatalogueError
    for any other non-empty folder."""
    if not out.exists() or not any(out.iterdir()):
        return {}
    try:
        files = json.loads((out / MANIFEST).read_text())["files"]
        if isinstance(files, dict) and all(isinstance(v, str) for v in files.values()):
            return {str(k): v for k, v in files.items() if _inside(out, str(k))}
    except (OSError, ValueError, KeyError, TypeError):
        pass
    if _generated_by_dammrl(out):
        return None
    raise CatalogueError(f"{out} is not empty and is no BIDS export of dammrl's: give a new folder")


def staging(out: Path) -> Path:
    """An empty folder to write the new export into."""
    folder = out / STAGING
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    return folder


def put_in_place(out: Path, staged: Path, previous: dict[str, str] | None,
                 authors_given: bool) -> Kept:  # fmt: skip
    """Move the staged export into ``out``, keeping the lab's work (module docstring)."""
    new = {p.relative_to(staged).as_posix(): p for p in sorted(staged.rglob("*")) if p.is_file()}
    old = previous or {}
    changed = {rel for rel, sha in old.items() if (out / rel).is_file() and _sha(out / rel) != sha}
    if previous is None:  # an export before the list: what may hold the lab's edits is merged
        changed = {rel for rel in new if (out / rel).is_file() and _mergeable(rel)}
    _write_manifest(out, dict.fromkeys(old, "") | dict.fromkeys(new, ""))
    for rel in set(old) - set(new) - changed:
        (out / rel).unlink(missing_ok=True)
    kept, written = Kept(), {}
    for rel, path in new.items():
        written[rel] = _sha(path)  # dammrl's own: a file differing from it is the lab's
        target = out / rel
        if rel in changed:
            merged = _mergeable(rel) and _merge(target, path, authors_given)
            (kept.merged if merged else kept.as_left).append(rel)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(path, target)
    _write_manifest(out, written)
    shutil.rmtree(staged, ignore_errors=True)
    _remove_empty_folders(out, set(old) - set(new))
    kept.added = _added(out, set(written))
    return kept


def _mergeable(rel: str) -> bool:
    return rel == "participants.tsv" or rel.endswith(".json")


def _merge(target: Path, staged: Path, authors_given: bool) -> bool:
    """dammrl's part merged into the lab's changed ``target``; False when it is kept as
    the lab left it (JSON that no longer parses as an object)."""
    if target.name == "participants.tsv":
        target.write_text(_merged_rows(target.read_text(), staged.read_text()))
        return True
    if target.suffix == ".json":
        try:
            lab = json.loads(target.read_text())
        except ValueError:
            return False
        ours = json.loads(staged.read_text())
        if not isinstance(lab, dict):
            return False
        forced = set(DAMMRL_SETS) | ({"Authors", "License"} if authors_given else set())
        if target.name != "dataset_description.json":
            forced = set()
        merged = ours | lab | {k: ours[k] for k in forced if k in ours}
        target.write_text(json.dumps(merged, indent=2) + "\n")
        return True
    return False


def _merged_rows(lab_text: str, ours_text: str) -> str:
    """dammrl's participants with the lab's columns (n/a where the lab has no value), then
    the lab's rows of participants dammrl does not export."""
    lab = list(csv.DictReader(io.StringIO(lab_text), delimiter="\t"))
    ours = list(csv.DictReader(io.StringIO(ours_text), delimiter="\t"))
    columns = ["participant_id"]
    for row in lab:
        columns += [c for c in row if c not in columns and c is not None]
    by_id = {row.get("participant_id"): row for row in lab}
    rows = [{c: (by_id.get(r["participant_id"]) or {}).get(c) or "n/a" for c in columns}
            | {"participant_id": r["participant_id"]} for r in ours]  # fmt: skip
    exported = {r["participant_id"] for r in ours}
    rows += [{c: row.get(c) or "n/a" for c in columns} for row in lab
             if row.get("participant_id") not in exported]  # fmt: skip
    text = io.StringIO()
    writer = csv.DictWriter(text, columns, delimiter="\t", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return text.getvalue()


def _added(out: Path, ours: set[str]) -> list[str]:
    """The lab's files, summed up by their top-level folder or file."""
    counts: Counter[str] = Counter()
    for path in out.rglob("*"):
        rel = path.relative_to(out).as_posix()
        if path.is_file() and rel not in ours and not rel.startswith(".dammrl/"):
            top = rel.split("/", 1)[0]
            counts[top + ("/" if "/" in rel else "")] += 1
    return [f"{top} ({n} files)" if top.endswith("/") and n > 1 else
            f"{top} (1 file)" if top.endswith("/") else top
            for top, n in sorted(counts.items())]  # fmt: skip


def _write_manifest(out: Path, files: dict[str, str]) -> None:
    path = out / MANIFEST
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".tmp")
    content = {"dammrl": __version__, "files": dict(sorted(files.items()))}
    temporary.write_text(json.dumps(content, indent=1) + "\n")
    os.replace(temporary, path)


def _remove_empty_folders(out: Path, removed: set[str]) -> None:
    """Folders that only held files dammrl no longer writes."""
    for rel in sorted(removed, key=lambda r: -r.count("/")):
        for parent in (out / rel).parents:
            if parent == out or not parent.is_dir() or any(parent.iterdir()):
                break
            parent.rmdir()


def _generated_by_dammrl(out: Path) -> bool:
    try:
        description = json.loads((out / "dataset_description.json").read_text())
        return bool(description["GeneratedBy"][0]["Name"] == "dammrl")
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return False


def _inside(out: Path, rel: str) -> bool:
    """A listed path that stays inside ``out`` (a crafted list must not reach out)."""
    resolved = (out / rel).resolve()
    return resolved.is_relative_to(out.resolve()) and not rel.startswith(".dammrl")


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
