"""The arm loop's scheduling priority reaches the processors' first share: the session."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from services.common.runtime import AUTOGROUP


def may_raise_priority() -> bool:
    """Linux's autogroup is here, and a process may raise its priority (root with
    CAP_SYS_NICE: not in every container)."""
    probe = "import os; os.setpriority(os.PRIO_PROCESS, 0, -1)"
    raised = subprocess.run([sys.executable, "-c", probe], capture_output=True, check=False)
    return Path(AUTOGROUP).exists() and raised.returncode == 0


pytestmark = pytest.mark.skipif(
    not may_raise_priority(), reason="Linux's autogroup, and the right to raise a priority"
)

PRIORITISED = (
    "from services.common.runtime import prioritise\n"
    "said = prioritise({critical})\n"
    "print(said + '|' + open('/proc/self/autogroup').read().strip())\n"
)


def _prioritised(critical: bool, own_session: bool) -> tuple[str, str]:
    """What the service said, and its session's autogroup as Linux shows it: "" for a
    session in the root's group (a service, or CI, started under init's session)."""
    done = subprocess.run(
        [sys.executable, "-c", PRIORITISED.format(critical=critical)],
        capture_output=True, text=True, timeout=60, check=True, start_new_session=own_session,
    )  # fmt: skip
    said, autogroup = done.stdout.strip().rsplit("|", 1)
    return said, autogroup


def _nice(autogroup: str) -> int:
    return int(autogroup.split("nice")[1])


def test_a_time_critical_service_leading_its_session_raises_the_sessions_priority() -> None:
    said, autogroup = _prioritised(critical=True, own_session=True)
    assert _nice(autogroup) == -10 and said == "scheduling priority nice -10, its session's too"


def test_a_service_in_someone_elses_session_leaves_that_session_as_it_was() -> None:
    before = Path(AUTOGROUP).read_text().strip()
    said, autogroup = _prioritised(critical=True, own_session=False)
    assert autogroup == before and said == "scheduling priority nice -10"


def test_a_service_that_is_not_time_critical_keeps_its_session_at_the_default() -> None:
    said, autogroup = _prioritised(critical=False, own_session=True)
    assert said == "scheduling priority nice 0, its session's too" and _nice(autogroup) == 0
