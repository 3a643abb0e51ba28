"""The arm loop's scheduling priority reaches the processors' first share: the session."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.common.runtime import AUTOGROUP

pytestmark = pytest.mark.skipif(
    not Path(AUTOGROUP).exists() or os.geteuid() != 0,
    reason="Linux's autogroup, and the right to raise a priority (root)",
)

PRIORITISED = (
    "from services.common.runtime import prioritise\n"
    "said = prioritise({critical})\n"
    "print(said + '|' + open('/proc/self/autogroup').read().split('nice')[1].strip())\n"
)


def _prioritised(critical: bool, own_session: bool) -> tuple[str, int]:
    done = subprocess.run(
        [sys.executable, "-c", PRIORITISED.format(critical=critical)],
        capture_output=True, text=True, timeout=60, check=True, start_new_session=own_session,
    )  # fmt: skip
    said, nice = done.stdout.strip().rsplit("|", 1)
    return said, int(nice)


def test_a_time_critical_service_leading_its_session_raises_the_sessions_priority() -> None:
    said, nice = _prioritised(critical=True, own_session=True)
    assert nice == -10 and said == "scheduling priority nice -10, its session's too"


def test_a_service_in_someone_elses_session_leaves_that_session_as_it_was() -> None:
    before = int(Path(AUTOGROUP).read_text().split("nice")[1])
    said, nice = _prioritised(critical=True, own_session=False)
    assert nice == before and said == "scheduling priority nice -10"


def test_a_service_that_is_not_time_critical_keeps_its_session_at_the_default() -> None:
    assert _prioritised(critical=False, own_session=True) == (
        "scheduling priority nice 0, its session's too",
        0,
    )
