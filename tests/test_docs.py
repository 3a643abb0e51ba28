"""The documentation's files reach a clean checkout: nothing a page links to may be left
out by .gitignore (five images once were, and `mkdocs build --strict` failed only in CI)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s#]+)")  # markdown links and images: ](target)


def _linked_files() -> list[Path]:
    pages = [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]
    linked = []
    for page in pages:
        for target in LINK.findall(page.read_text()):
            if "://" not in target and not target.startswith("mailto:"):
                linked.append((page.parent / target).resolve())
    return linked


@pytest.mark.skipif(
    shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout"
)
def test_no_file_a_page_links_to_is_ignored_by_git() -> None:
    files = [str(path.relative_to(ROOT)) for path in _linked_files() if path.is_file()]
    ignored = subprocess.run(
        ["git", "check-ignore", "--no-index", *files], cwd=ROOT, capture_output=True, text=True
    ).stdout.split()
    assert ignored == []


def test_every_file_a_page_links_to_exists() -> None:
    missing = [str(path) for path in _linked_files() if not path.exists()]
    assert missing == []
