"""The emulated servo chain on a pseudo-terminal: any Protocol 2.0 host (the official
dynamixel-sdk included) opens the linked path like a USB servo adapter."""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from pathlib import Path
from types import TracebackType

from dammrl.devices.emulators.protocol2 import PacketReader
from dammrl.devices.emulators.servo_chain import ServoChain

TICK_S = 0.002  # the chain's clock advances at least this often while idle


class ServoBusEmulator:
    """Serves ``chain`` on a pty linked at ``link`` until closed (a context manager)."""

    def __init__(self, chain: ServoChain, link: Path) -> None:
        self.chain, self.link = chain, Path(link)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # bytes as they are: no echo, no line discipline
        if self.link.is_symlink() or self.link.exists():
            self.link.unlink()
        self.link.symlink_to(os.ttyname(self._slave))
        self._stop = threading.Event()
        self._lock = threading.Lock()  # the chain is read by tests while served
        self._started = time.monotonic()
        self._thread = threading.Thread(target=self._serve, name="servo-bus", daemon=True)
        self._thread.start()

    def __enter__(self) -> ServoBusEmulator:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 trace: TracebackType | None) -> None:  # fmt: skip
        self.close()

    @property
    def lock(self) -> threading.Lock:
        return self._lock

    def close(self) -> None:
        self.pull_out()
        if self._slave >= 0:
            os.close(self._slave)
            self._slave = -1
        self.link.unlink(missing_ok=True)

    def pull_out(self) -> None:
        """The USB adapter pulled out: the device hangs up under whoever has it open (a
        read or a flush fails), unlike ``unplug`` faults, which only silence the servos."""
        self._stop.set()
        self._thread.join(2.0)
        if self._master >= 0:
            os.close(self._master)
            self._master = -1

    def _serve(self) -> None:
        reader = PacketReader()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], TICK_S)
            data = os.read(self._master, 4096) if ready else b""
            with self._lock:
                self.chain.advance(time.monotonic() - self._started)
                if self.chain.faults.unplugged:
                    continue  # bytes go nowhere
                for packet in reader.feed(data):
                    for response in self.chain.handle(packet):
                        os.write(self._master, response)
