"""Process plumbing shared by the service entry points: signals and a paced loop."""

from __future__ import annotations

import contextlib
import gc
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""What stops a service or a tool cleanly: Ctrl-C, a stop, a hang-up (its terminal, or
its launcher's death: ``dammrl up`` asks for SIGHUP as its children's parent-death
signal, so that they can tell it from a stop)."""
TIME_CRITICAL = ("sim", "robot", "controller")
"""The services that close the arm's loop (a late state or command stalls the arm; the
real arm's own loop feeds its servos' 0.1 s watchdog)."""
CRITICAL_NICE = -10
CRITICAL_SWITCH_INTERVAL_S = 0.0002


def prioritise(critical: bool) -> str:
    """Set this process's scheduling priority: ``CRITICAL_NICE`` for a time-critical one,
    the default otherwise (a launcher's children inherit its own). Call it before opening
    the Zenoh session: on Linux a priority is per thread, and threads inherit it when they
    start. Returns what it did, for the log."""
    wanted = CRITICAL_NICE if critical else 0
    if critical:
        # the loop's thread takes the GIL back within this, however busy Zenoh's callback
        # threads are (Python's default, 5 ms, is half a period per GIL hand-over)
        sys.setswitchinterval(CRITICAL_SWITCH_INTERVAL_S)
    try:
        os.setpriority(os.PRIO_PROCESS, 0, wanted)
    except PermissionError:
        now = os.getpriority(os.PRIO_PROCESS, 0)
        return f"scheduling priority left at nice {now} (nice {wanted} needs CAP_SYS_NICE)"
    return f"scheduling priority nice {wanted}{_session_priority(wanted)}"


AUTOGROUP = "/proc/self/autogroup"
"""Linux's scheduler shares the processors between sessions first (autogroup, on by
default where a process's cgroup is the root's) and weighs a nice value only within its
session: a service leading its own session (``dammrl up`` starts each so) at nice -10 got no
more of a busy processor than any program beside it. Measured on the 2-core machine, a
2 ms loop beside two CPU hogs and four busy sessions: late by p99 6.7 ms (max 12.7) at nice
-10 alone, 0.1 ms (max 5.7) with its session's nice -10 too; in a running stack, stalls of
the controller of 0.11-0.15 s spent waiting for a CPU."""


def _session_priority(nice: int) -> str:
    """Give this process's session (Linux's autogroup) the same nice, when it leads it: a
    session of its own is the service alone (never a terminal's shell and what it runs)."""
    if os.getsid(0) != os.getpid():
        return ""
    try:
        with open(AUTOGROUP, "w") as autogroup:
            autogroup.write(str(nice))
    except OSError:  # no autogroup in this kernel, or not allowed
        return ""
    return ", its session's too"


def cpu_wait_s() -> float | None:
    """How long the calling thread has waited for a CPU since it started, ready to run
    [s] (Linux's schedstat; None elsewhere): a stall it grew by was the PC's, not the
    thread's own work."""
    try:
        with open("/proc/thread-self/schedstat") as stat:
            return int(stat.read().split()[1]) * 1e-9
    except (OSError, IndexError, ValueError):
        return None


def freeze_startup_heap() -> None:
    """Collect once, then put every object made at start-up beyond the garbage collector
    (``gc.freeze``): later full collections scan only what the loop made since, not the
    libraries' heaps (MuJoCo's, pinocchio's, pydantic's, Zenoh's). Before, in a quiet
    4-reach `dammrl up`, full collections paused the sim 51-89 ms and the controller
    30-84 ms in the first seconds after the services were alive, as the first reach
    starts (beside two CPU hogs: a state 0.1 s late, commands answering states too old);
    after, none over 3 ms while the services run."""
    gc.collect()
    gc.freeze()


class SignalStop(threading.Event):
    """An event set by SIGINT, SIGTERM or SIGHUP; ``signum`` is the one that arrived (0:
    none).

    The handler takes no lock: Python runs it in the main thread between any two
    bytecodes, also inside this event's own ``wait`` while that holds the lock ``set``
    needs, and setting it there deadlocks (Python's signal docs warn of locks in
    handlers; a service once hung so, ignoring its launcher's death and every later
    signal). The handler writes a byte to a pipe; a thread of its own sets the event."""

    def __init__(self) -> None:
        super().__init__()
        self.signum = 0
        read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._write_fd, False)
        threading.Thread(
            target=self._set_when_signalled, args=(read_fd,), name="signal-stop", daemon=True
        ).start()

    def handle(self, signum: int, frame: object) -> None:
        """The signal handler: remember the signal and wake the thread that sets the event
        (os.write takes no Python lock)."""
        self.signum = signum
        if self._write_fd >= 0:
            with contextlib.suppress(OSError):  # full: a byte is already waiting
                os.write(self._write_fd, b"\0")

    def _set_when_signalled(self, read_fd: int) -> None:
        try:
            while os.read(read_fd, 1):  # b"": closed, no signal will come
                self.set()
        finally:
            os.close(read_fd)

    def close(self) -> None:
        """No more signals: the setting thread ends."""
        write_fd, self._write_fd = self._write_fd, -1  # first: a late handler writes nothing
        if write_fd >= 0:
            os.close(write_fd)


def stop_on_signals() -> SignalStop:
    """An event set by SIGINT, SIGTERM or SIGHUP, so loops end cleanly and ``finally``
    runs."""
    stop = SignalStop()
    for signum in SIGNALS:
        signal.signal(signum, stop.handle)
    return stop


EXIT_GRACE_S = 5.0
"""After a stopping signal a service has this long to stop cleanly, then it exits anyway."""


def exit_within(stop: SignalStop, grace_s: float = EXIT_GRACE_S) -> None:
    """Make this process end within ``grace_s`` of ``stop`` being set, for whatever
    reason (SIGINT, SIGTERM, its launcher gone), whatever its threads are doing.

    Python runs signal handlers in the main thread only, between bytecodes: a main
    thread blocked in native code (a Zenoh call waiting on a futex for a peer that is
    gone) would never see them. The kernel's signal still writes to a wakeup file
    descriptor, which a watcher thread reads to set ``stop``. A second thread gives the
    clean end ``grace_s``, then exits (code 128 + signal, or 1) taking no lock: a stderr
    pipe nobody reads holds the logging locks forever, ``logging.shutdown`` included.
    Call it from the main thread, after ``stop_on_signals``."""
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    threading.Thread(
        target=_stop_on_wakeup, args=(read_fd, stop), name="signal-wakeup", daemon=True
    ).start()
    threading.Thread(
        target=_exit_after_grace, args=(stop, grace_s), name="exit-within", daemon=True
    ).start()


def _stop_on_wakeup(read_fd: int, stop: SignalStop) -> None:
    signum = 0
    while signum not in SIGNALS:  # every handled signal writes its number
        signum = os.read(read_fd, 1)[0]
    stop.signum = stop.signum or signum
    stop.set()


def _exit_after_grace(stop: SignalStop, grace_s: float) -> None:
    stop.wait()
    time.sleep(grace_s)
    _say_if_stderr_takes_it(f"still running {grace_s:.0f} s after being asked to stop: "
                            "exiting without a clean stop\n")  # fmt: skip
    os._exit(128 + stop.signum if stop.signum else 1)


def _say_if_stderr_takes_it(line: str) -> None:
    """Write ``line`` to stderr only if that cannot block (a full pipe takes nothing)."""
    with contextlib.suppress(OSError, ValueError):
        if select.select([], [2], [], 0)[1]:  # room for a page: a short line fits
            os.write(2, line.encode()[: select.PIPE_BUF])


@contextmanager
def stopping_on_signals() -> Iterator[SignalStop]:
    """``stop_on_signals`` for a ``with`` block: the previous handlers return after it."""
    previous = {signum: signal.getsignal(signum) for signum in SIGNALS}
    stop = stop_on_signals()
    try:
        yield stop
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        stop.close()


class Pacer:
    """Keeps a loop at a fixed period in wall time and counts missed deadlines."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.next_s = time.monotonic()
        self.ticks = 0
        self.missed = 0

    def restart(self) -> None:
        """Start counting from now (call when the loop begins)."""
        self.next_s = time.monotonic()
        self.ticks = self.missed = 0

    def wait(self, idle: Callable[[float], object] = time.sleep) -> None:
        """Wait until the next deadline, handing the time left to ``idle(seconds)`` until
        it is over (default: sleep; a loop that answers messages as they arrive passes a
        bounded wait for them); a loop more than a period late starts afresh."""
        self.ticks += 1
        self.next_s += self.period_s
        delay = self.next_s - time.monotonic()
        if delay > 0:
            while delay > 0:
                idle(delay)
                delay = self.next_s - time.monotonic()
        elif delay < -self.period_s:
            self.missed += 1
            self.next_s = time.monotonic()
        else:
            self.missed += 1
