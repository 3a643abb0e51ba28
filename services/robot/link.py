"""The robot service's link to the arm's drives: connecting, a lost bus, holding blind,
the soft start after a torque-on (on its own clock: dammrl_core.arm.start), and the
drives' own stop after a silent host."""

from __future__ import annotations

import contextlib
import logging
import time

from dammrl_core.arm.driver import DriveCommand, Driver, DriverError, HoldLaw, JointState
from dammrl_core.arm.settings import ArmSettings
from dammrl_core.arm.start import LATE_CYCLE_S, SoftStart

log = logging.getLogger("dammrl.robot")


class DriveLink:
    """A driver and what is known of its connection."""

    def __init__(self, driver: Driver, settings: ArmSettings) -> None:
        self.driver = driver
        self.settings = settings
        self.connected = False
        self.limp = False  # a stop turned the torque off: the state is read, nothing written
        self.fault: str | None = None  # the bus is gone: reconnecting
        self.max_step_s = LATE_CYCLE_S  # what a late cycle advances the soft start by, at most
        self.ramp = SoftStart.begin(0.0, 1.0, self.max_step_s, 0.0, done=True)
        self.next_connect_s = 0.0
        self.errors = 0  # failed cycles in a row
        self.bus_errors = 0  # failed cycles since the start (Health says how many)
        self.last_written: DriveCommand | None = None  # the law last sent to the drives
        self.last_write_s = float("inf")  # when (monotonic); inf: not since connecting
        # a cycle failed since the drives were last asked: they keep their own clock, so a
        # packet held back (a busy PC, a USB adapter's buffer) can let their watchdog see
        # a longer silence than this host's clock did
        self.doubt_drives = False

    def try_connect(self, now: float, hold: HoldLaw) -> bool:
        """Connect when it is time to try, the drives holding with ``hold``'s law from
        their torque-on (at the soft start's first share); whether it just connected."""
        if now < self.next_connect_s:
            return False
        self.next_connect_s = now + self.settings.reconnect_s
        settings = self.settings
        self.ramp = SoftStart.begin(settings.soft_start_s, settings.soft_start_fraction,
                                    self.max_step_s, now)  # fmt: skip
        try:  # a torque-off stop outlives a lost bus: the drives come back limp
            holding = (
                self.driver.connect(torque=False) if self.limp else self.driver.connect(hold=hold)
            )
        except DriverError as exc:
            if self.fault != str(exc):
                log.error("%s: retrying every %.1f s", exc, self.settings.reconnect_s)
            self.fault = str(exc)
            return False
        # drives that held with the torque on: no soft start (it would let their joints sag)
        self.connected = True
        if holding:
            self.ramp = SoftStart.begin(0.0, 1.0, self.max_step_s, now, done=True)
        self.last_write_s = float("inf")  # connect armed the drives' watchdog: no stall yet
        if self.fault is not None:
            log.warning(
                "the drives' bus answers again: %s",
                "the torque stays off (the stop)" if self.limp else "holding where the arm is",
            )
        self.fault, self.errors = None, 0
        return True

    def read(self) -> JointState:
        return self.driver.read_state()

    def write(self, law: DriveCommand, now: float) -> None:
        self.driver.write_command(law)
        self.last_written, self.last_write_s = law, now

    def cycle_done(self) -> None:
        self.errors = 0

    def failed(self, exc: DriverError) -> bool:
        """A failed cycle (the drives keep their last goal); whether the bus is lost (too
        many in a row). Then the last law keeps being sent blind: the drives that still
        hear it hold with gravity compensation; the others' watchdog stops them."""
        self.errors += 1
        self.bus_errors += 1
        self.doubt_drives = True
        if self.errors < self.settings.max_bus_errors:
            log.warning("bus cycle failed (%d in a row): %s", self.errors, exc)
            return False
        self.fault = f"drives' bus lost: {exc}"
        log.error("%s: holding blind, reconnecting", self.fault)
        self.connected = False
        self.next_connect_s = time.monotonic() + self.settings.reconnect_s
        return True

    def hold_blind(self) -> None:
        """The last law sent again to the drives that may still hear it (not after a
        torque-off stop: that law is the motion the stop ended)."""
        if self.last_written is not None and not self.limp:
            with contextlib.suppress(DriverError):
                self.driver.write_command(self.last_written)

    def torque_off(self) -> None:
        """The stop's torque-off; nothing is written until a release reconnects (a
        reconnection meanwhile turns the torque off again)."""
        if not self.connected:
            log.error("the stop's torque-off cannot reach the drives (their bus is lost): use "
                      "the hardware stop; they come back limp")  # fmt: skip
        elif failed := self.driver.torque_off():
            log.error("the drives %s did not take the stop's torque-off: use the hardware stop",
                      failed)  # fmt: skip
        self.limp = True

    def reconnect_now(self) -> None:
        """Torque back on (after a torque-off stop was released), with the soft start."""
        if self.connected:
            self.driver.disconnect()
        self.connected = self.limp = False
        self.next_connect_s = 0.0

    def stalled(self, now: float) -> bool:
        """The drives may have stopped themselves: this process was silent longer than
        their own stop allows, by its clock, or a cycle failed since they were last asked
        (by their clock the silence may have been longer)."""
        stall_s = self.driver.stall_s
        if stall_s is None or self.limp:  # limp: nothing is written, the torque is off
            return False
        return self.doubt_drives or now - self.last_write_s > stall_s

    def soft_start(self, now: float) -> float:
        """The stiffness's share after torque-on: from ``soft_start_fraction`` to 1."""
        return self.ramp.share(now)

    def close(self) -> None:
        if self.connected:
            self.driver.disconnect()  # the drives hold where they are
