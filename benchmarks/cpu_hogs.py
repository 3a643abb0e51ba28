"""Other programs keeping the PC busy, as a lab's PC is: ``yes > /dev/null`` per hog
(the benchmarks that measure beside a load import it as a sibling)."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def hogs(count: int) -> Iterator[None]:
    """``count`` times ``yes > /dev/null``: another program keeping the PC busy."""
    busy = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(count)]
    try:
        yield
    finally:
        for hog in busy:
            hog.kill()
            hog.wait()
