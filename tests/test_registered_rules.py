"""The claim rules cover the judging: every file that turns reaches into verdicts is hashed,
and changing any of them without registering a new rules version fails here."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from dammrl.study import registry
from dammrl.study.claims import CLAIMS_VERSION, RULE_FILES

ROOT = Path(__file__).resolve().parent.parent


def test_the_judging_files_are_the_registered_version() -> None:
    hashes = registry.file_hashes()
    changed = registry.unregistered_changes(hashes)
    assert not changed, (
        f"{', '.join(changed)} changed but CLAIMS_VERSION is still {CLAIMS_VERSION}: a change "
        "of the judging is a new rules version (bump CLAIMS_VERSION, run `python -m "
        "dammrl.study.registry`, commit it before any study runs under it)"
    )


def test_the_rules_cover_every_file_that_turns_reaches_into_verdicts() -> None:
    """The claims, the inference (tests, intervals, Holm), the configurations, a reach's
    row and the metrics; the modules the judging imports are among them."""
    import dammrl.study.claims as claims
    import dammrl.study.inference as inference
    import dammrl.study.rows as rows

    covered = {registry.rule_path(name).resolve() for name in RULE_FILES}
    for module in (claims, inference, rows):
        assert Path(module.__file__ or "").resolve() in covered
    judged_from = {"dammrl.study.configs", "dammrl.study.inference", "dammrl.study.stats",
                   "dammrl_core.metrics", "dammrl.study.claims"}  # fmt: skip
    for module in (claims, inference, rows):
        source = Path(module.__file__ or "").read_text()
        for name in judged_from:
            if f"from {name} import" in source and name != "dammrl.study.stats":
                assert f"{name.replace('.', '/')}.py" in RULE_FILES, name
    # inference reads only Estimate and NO_DATA from stats: a container, no judging
    assert (
        "from dammrl.study.stats import NO_DATA, Estimate"
        in Path(inference.__file__ or "").read_text()
    )


@pytest.mark.parametrize("name", RULE_FILES)
def test_editing_any_judging_file_without_a_new_version_is_caught(
    name: str, tmp_path: Path
) -> None:
    """A copy of the rule files with one byte changed in ``name`` (study v2's audit halved
    every p-value by editing a file the hash did not cover)."""
    for rule in RULE_FILES:
        (tmp_path / rule).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(registry.rule_path(rule), tmp_path / rule)
    assert registry.unregistered_changes(registry.file_hashes(tmp_path)) == []
    edited = tmp_path / name
    edited.write_text(edited.read_text().replace("0", "1", 1))
    assert registry.unregistered_changes(registry.file_hashes(tmp_path)) == [name]


def test_a_registered_version_is_never_overwritten(tmp_path: Path) -> None:
    copy = tmp_path / "registered_rules.json"
    shutil.copy(registry.REGISTRY, copy)
    with pytest.raises(ValueError, match="registered already"):
        registry.register(CLAIMS_VERSION, copy)
    registry.register(CLAIMS_VERSION + 1, copy)
    document = json.loads(copy.read_text())
    assert document[str(CLAIMS_VERSION + 1)]["files"] == registry.file_hashes()
    assert registry.registered(CLAIMS_VERSION + 2, copy) == {}  # unknown: nothing matches
    assert registry.unregistered_changes(registry.file_hashes(), CLAIMS_VERSION + 2, copy) == list(
        RULE_FILES
    )


def test_the_rule_files_are_read_from_the_packages_in_use() -> None:
    for name in RULE_FILES:
        assert registry.rule_path(name).resolve() == (ROOT / name).resolve()
