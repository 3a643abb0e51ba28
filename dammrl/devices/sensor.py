"""``dammrl sensor``: the pressure pad in the terminal (calibrate, monitor, emulate).

Each tool reads the port through the same :class:`SerialSensor` and decodes with the same
:class:`PressDecoder` as the intent service, so what the monitor shows is what the stack
will do.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import sys
import termios
import threading
import time
import tty
from collections import deque
from collections.abc import Callable, Iterator

from dammrl.devices.emulators.pad import SensorEmulator
from dammrl_core.errors import DammrlError
from dammrl_core.intent.pad.calibration import (
    CalibrationError,
    Rest,
    calibration_from,
    held_press,
    rest_of,
)
from dammrl_core.intent.pad.decoder import Calibration, DecoderSettings, PressDecision, PressDecoder
from dammrl_core.intent.pad.serial import Arrival, SerialSensor
from dammrl_core.models import ModelSet, radius_name

BAR_WIDTH = 40
BAR_TOP = 1.25  # normalised level at the right end of the bar
CHECK_S = 2.0  # how long to wait for the first valid frame


def describe(decision: PressDecision, models: ModelSet) -> str:
    direction = "+1 forward (firm)" if decision.u_h > 0 else "-1 back (light)"
    radius = radius_name(decision.human_model)
    kind = "quick" if decision.human_model == 1 else "held"
    radius_mm = models.radius_m(decision.human_model) * 1000
    return (
        f"{direction:17s}  {kind} {decision.duration_s:4.2f} s -> {radius} "
        f"({radius_mm:.0f} mm)  peak {decision.peak:4.2f}  confidence {decision.confidence:4.2f}"
    )


def level_bar(level: float, marks: dict[float, str]) -> str:
    """``[####....|....]``: the level as a bar, with marks (e.g. the firm boundary)."""
    cells = ["#" if (k + 0.5) / BAR_WIDTH * BAR_TOP <= level else "." for k in range(BAR_WIDTH)]
    for at, mark in marks.items():
        cells[min(BAR_WIDTH - 1, int(at / BAR_TOP * BAR_WIDTH))] = mark
    return "[" + "".join(cells) + "]"


def quiet_reader() -> None:
    """The terminal tools say themselves what the reader would log (lost port, retries)."""
    logging.getLogger("dammrl.intent").setLevel(logging.ERROR)


def wait_for_frames(sensor: SerialSensor) -> None:
    deadline = time.monotonic() + CHECK_S
    while time.monotonic() < deadline:
        if sensor.read():
            return
    bad = dict(sensor.parser.errors) or "none"
    reason = sensor.last_error or f"bad frames: {bad}"
    raise DammrlError(
        f"no valid frame from {sensor.device} in {CHECK_S:.0f} s ({reason}). Is the sensor "
        f"plugged in and sending at {sensor.baud_rate} baud? (dammrl sensor list)"
    )


# --- monitor -----------------------------------------------------------------------------


class Monitor:
    """Live pressure, press state and decoded decisions, redrawn in place on a terminal."""

    def __init__(self, sensor: SerialSensor, decoder: PressDecoder, models: ModelSet) -> None:
        self.sensor = sensor
        self.decoder = decoder
        self.models = models
        self.decisions: deque[str] = deque(maxlen=5)
        self.count = 0
        self.raw = 0
        self.arrivals: deque[float] = deque()  # frame times of the last second
        self._drawn = 0

    def run(self, stop: threading.Event, redraw_s: float = 0.05) -> None:
        tty_out = sys.stdout.isatty()
        print(self.header(), flush=True)
        next_draw = 0.0
        while not stop.is_set():
            for arrival in self.sensor.read():
                self._sample(arrival, tty_out)
            if not self.sensor.connected:
                self.decoder.reset()  # as the intent service: no press spans a disconnect
            now = time.monotonic()
            if now >= next_draw:
                self._draw(tty_out)
                next_draw = now + (redraw_s if tty_out else 1.0)

    def header(self) -> str:
        c, d = self.decoder.calibration, self.decoder
        big, small = (self.models.radius_m(i) * 1000 for i in (1, 2))
        return (
            f"Pressure sensor on {self.sensor.device} ({self.sensor.baud_rate} baud). "
            f"Calibration: rest {c.rest_raw:.0f}, light {c.light_raw:.0f}, firm {c.firm_raw:.0f}"
            f" raw.\nA press is one command when it ends: FIRM (above the | mark) = +1 forward,"
            f" light = -1 back;\nquick (< {d.settings.long_press_s} s) = E_big ({big:.0f} mm),"
            f" held = E_small ({small:.0f} mm). Ctrl-C stops.\n"
        )

    def _sample(self, arrival: Arrival, tty_out: bool) -> None:
        t_s, self.raw = arrival.t_s, arrival.frame.raw
        self.arrivals.append(t_s)
        while self.arrivals and self.arrivals[0] < t_s - 1.0:
            self.arrivals.popleft()
        decision = self.decoder.update(arrival.sampled_s, self.raw, arrival.lost_frames)
        if decision is None:
            return
        self.count += 1
        line = f"#{self.count:<3d} {describe(decision, self.models)}"
        self.decisions.appendleft(line)
        if not tty_out:
            print(line, flush=True)

    def status_lines(self) -> list[str]:
        d, s = self.decoder, self.sensor
        bar = level_bar(d.level, {d.firm_level: "|"})
        if not s.connected:
            link = f"NOT CONNECTED, retrying ({s.last_error})"
        elif s.silent_for() > 0.5:
            link = f"SILENT for {s.silent_for():.1f} s: no valid frame"
        else:
            link = f"{len(self.arrivals)} frames/s"
        bad = sum(s.parser.errors.values())
        errors = ", ".join(f"{k} {v}" for k, v in s.parser.errors.items()) or "none"
        return [
            f"pressure {bar} {max(d.level, 0.0):4.2f}  raw {self.raw:4d}  {press_state(d)}",
            f"sensor   {link}, {s.parser.frames} frames, {bad} bad ({errors})",
        ]

    def _draw(self, tty_out: bool) -> None:
        lines = self.status_lines()
        if not tty_out:
            print(" | ".join(lines), flush=True)
            return
        lines += ["decisions (newest first):"] + [f"  {d}" for d in self.decisions]
        width = shutil.get_terminal_size().columns - 1  # a wrapped line would break the redraw
        up = f"\x1b[{self._drawn}F" if self._drawn else ""
        sys.stdout.write(up + "".join(f"\x1b[2K{line[:width]}\n" for line in lines))
        sys.stdout.flush()
        self._drawn = len(lines)


def press_state(decoder: PressDecoder) -> str:
    """What the decoder makes of the pad now, in a few words."""
    now, stuck, high = time.monotonic(), decoder.stuck_since, decoder.high_since
    if stuck is not None:
        return f"STUCK {now - stuck:3.0f} s: no command until the pad is at rest"
    if decoder.pressing_since is not None:
        return f"PRESSED {now - decoder.pressing_since:3.1f} s"
    if high is not None:
        return "pressed, not counted: release the pad first"  # since before a reset
    return "rest" if decoder.armed else "waiting for rest"


# --- calibrate ---------------------------------------------------------------------------

STEPS = (
    ("REST", "Take your hand off the pad and keep still until the recording ends."),
    ("LIGHT", "Press the pad LIGHTLY (a 'back' command) and hold it until the recording ends."),
    ("FIRM", "Press the pad FIRMLY (as hard as is comfortable) and hold it until the end."),
)


def record(sensor: SerialSensor, seconds: float, show: Callable[[str], None]) -> list[int]:
    """The raw readings of ``seconds``, with a progress bar."""
    raws: list[int] = []
    start = time.monotonic()
    while (elapsed := time.monotonic() - start) < seconds:
        raws.extend(a.frame.raw for a in sensor.read())
        filled = int(20 * elapsed / seconds)
        last = raws[-1] if raws else 0
        show(f"  recording [{'#' * filled}{'-' * (20 - filled)}] {elapsed:3.1f}/{seconds:.0f} s"
             f"  raw {last:4d}")  # fmt: skip
    show("")
    return raws


def calibrate(
    sensor: SerialSensor,
    seconds: float,
    ready: Callable[[str], None],
    show: Callable[[str], None],
    tries: int = 3,
    decoder: DecoderSettings | None = None,
) -> Calibration:
    """Guide rest, light and firm recordings; a failed step is explained and repeated; the
    result must suit the ``decoder``'s thresholds (the intent service's), or what to redo
    is explained."""
    wait_for_frames(sensor)
    rest: Rest | None = None
    levels: dict[str, float] = {}
    for number, (name, instruction) in enumerate(STEPS, 1):
        for attempt in range(1, tries + 1):
            ready(f"Step {number}/3 - {name}: {instruction}")
            raws = record(sensor, seconds, show)
            try:
                if rest is None:
                    rest = rest_of(raws)
                    summary = f"rest reads {rest.raw:.0f} (noise +/-{rest.noise_raw:.0f})"
                else:
                    levels[name] = held_press(raws, rest, name.lower())
                    summary = f"{name.lower()} press reads {levels[name]:.0f}"
            except CalibrationError as exc:
                if attempt == tries:
                    raise
                show(f"  ! {exc}\n  Let's try that step again.\n")
                continue
            show(f"  ok: {summary}\n")
            break
    assert rest is not None
    return calibration_from(rest, levels["LIGHT"], levels["FIRM"], decoder)


# --- emulate -----------------------------------------------------------------------------

KEYS = """keys:  f / l   quick FIRM / LIGHT press (+1 / -1, E_big)
       F / L   held FIRM / LIGHT press (+1 / -1, E_small)
       1 .. 9  hold the pad at 10 .. 90 % (for calibrate), 0 releases
       x       corrupt the next 5 frames    d  a 1 s drop-out    q  quit"""


def keyboard(sensor: SensorEmulator, stop: threading.Event) -> None:
    """Drive the emulated pad from the keyboard until ``q`` or ``stop``."""
    with raw_keys() as read_key:
        while not stop.is_set():
            key = read_key(0.1)
            if key == "q":
                return
            if key is not None:
                press_key(sensor, key)


def press_key(sensor: SensorEmulator, key: str) -> None:
    quick, held = 0.2, 0.8
    actions: dict[str, Callable[[], None]] = {
        "f": lambda: sensor.press(0.95, quick),
        "l": lambda: sensor.press(0.35, quick),
        "F": lambda: sensor.press(0.95, held),
        "L": lambda: sensor.press(0.35, held),
        "x": lambda: setattr(sensor, "corrupt_next", 5),
        "d": lambda: drop_out(sensor, 1.0),
    }
    if key.isdigit():
        sensor.hold(int(key) / 10)
        print(f"\rholding at {int(key) * 10} %   " if key != "0" else "\rreleased        ", end="")
    elif key in actions:
        actions[key]()
    sys.stdout.flush()


def drop_out(sensor: SensorEmulator, seconds: float) -> None:
    sensor.silent.set()
    timer = threading.Timer(seconds, sensor.silent.clear)
    timer.daemon = True
    timer.start()


@contextlib.contextmanager
def raw_keys() -> Iterator[Callable[[float], str | None]]:
    """Single key presses from the terminal, without Enter; restores the terminal."""
    import select

    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)

    def read_key(timeout_s: float) -> str | None:
        ready, _, _ = select.select([fd], [], [], timeout_s)
        return sys.stdin.read(1) if ready else None

    try:
        tty.setcbreak(fd)
        yield read_key
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)
