"""`dammrl sensor calibrate|monitor|emulate` against the emulated pad on a real pty."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from dammrl.devices.emulators.pad import DEFAULT_CALIBRATION, Press, SensorEmulator
from dammrl.devices.sensor import calibrate
from dammrl_core.errors import ConfigurationError, Exit
from dammrl_core.intent.pad.calibration import (
    CalibrationError,
    Rest,
    calibration_from,
    held_press,
    load_calibration,
    rest_of,
)
from dammrl_core.intent.pad.serial import SerialSensor

HOLD_LEVELS = {"REST": 0.0, "LIGHT": 0.3, "FIRM": 0.9}


def test_rest_and_press_levels_are_robust_to_the_moments_before_pressing() -> None:
    rest = rest_of([400, 410, 390, 405, 395] * 10)
    assert rest.raw == 400 and 5 < rest.noise_raw < 15
    recording = [400] * 40 + [1500] * 60  # the person starts pressing 0.4 s late
    assert held_press(recording, rest, "light") == 1500


@pytest.mark.parametrize(
    ("light", "firm", "complaint"),
    [(1500, 1400, "not harder"), (1500, 1600, "too close")],
)
def test_presses_that_cannot_be_told_apart_are_refused_with_advice(
    light: float, firm: float, complaint: str
) -> None:
    with pytest.raises(CalibrationError, match=complaint):
        calibration_from(Rest(400, 10), light, firm)


def test_a_step_without_a_held_press_is_refused() -> None:
    with pytest.raises(CalibrationError, match="Press and hold"):
        held_press([400] * 90 + [1500] * 10, Rest(400, 10), "firm")


def test_guided_calibration_recovers_the_pads_levels_and_the_file_loads(tmp_path: Path) -> None:
    link = tmp_path / "ttySENSOR"
    shown: list[str] = []
    with SensorEmulator(link, []) as pad, SerialSensor(str(link)) as sensor:

        def ready(step: str) -> None:  # the person does what the step asks
            shown.append(step)
            pad.hold(HOLD_LEVELS[step.split(" - ")[1].split(":")[0]])

        calibration = calibrate(sensor, 0.6, ready, shown.append)
    c = DEFAULT_CALIBRATION
    span = c.firm_raw - c.rest_raw
    assert abs(calibration.rest_raw - c.rest_raw) < 15
    assert abs(calibration.light_raw - (c.rest_raw + 0.3 * span)) < 20
    assert abs(calibration.firm_raw - (c.rest_raw + 0.9 * span)) < 20
    assert calibration.rest_noise_raw is not None and 8 < calibration.rest_noise_raw < 16
    assert any("Step 3/3 - FIRM" in line for line in shown)
    path = tmp_path / "calibration.json"
    path.write_text(calibration.model_dump_json())
    assert load_calibration(path) == calibration


def test_a_failed_step_is_explained_and_repeated(tmp_path: Path) -> None:
    link = tmp_path / "ttySENSOR"
    shown: list[str] = []
    with SensorEmulator(link, []) as pad, SerialSensor(str(link)) as sensor:
        asked: list[str] = []

        def ready(step: str) -> None:
            asked.append(step)
            name = step.split(" - ")[1].split(":")[0]
            forgot = name == "LIGHT" and asked.count(step) == 1  # forgets to press once
            pad.hold(0.0 if forgot else HOLD_LEVELS[name])

        calibrate(sensor, 0.5, ready, shown.append)
    assert sum("LIGHT" in step for step in asked) == 2
    assert any("no light press held" in line for line in shown)


def test_a_bad_calibration_file_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    path.write_text(DEFAULT_CALIBRATION.model_dump_json()[:-3])
    with pytest.raises(ConfigurationError, match="not a valid calibration file"):
        load_calibration(path)
    with pytest.raises(ConfigurationError, match="cannot read"):
        load_calibration(tmp_path / "missing.json")


def _dammrl(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "dammrl", *args]
    environment = os.environ | env
    return subprocess.run(command, capture_output=True, text=True, timeout=30, env=environment)


def test_monitor_prints_each_decoded_press(tmp_path: Path) -> None:
    link = tmp_path / "ttySENSOR"
    script = [Press(0.3, 0.25, 1.0), Press(1.0, 0.8, 0.35)]
    with SensorEmulator(link, script, loop_s=2.0):
        done = _dammrl("sensor", "monitor", "--port", str(link), "--seconds", "3")
    assert done.returncode == 0, done.stderr
    assert "+1 forward (firm)  quick" in done.stdout
    assert "-1 back (light)    held" in done.stdout and "E_small" in done.stdout
    assert "frames/s" in done.stdout


def test_monitor_uses_the_intent_services_decoder_settings(tmp_path: Path) -> None:
    link = tmp_path / "ttySENSOR"
    with SensorEmulator(link, [Press(0.3, 0.8, 0.35)], loop_s=1.5):
        done = _dammrl(
            "sensor", "monitor", "--port", str(link), "--seconds", "2.5",
            DAMMRL_PAD_DECODER__LONG_PRESS_S="1.2",
        )  # fmt: skip
    assert "-1 back (light)    quick" in done.stdout, done.stdout + done.stderr


def test_monitor_and_calibrate_say_when_no_sensor_answers(tmp_path: Path) -> None:
    for action in (["monitor"], ["calibrate", "--yes"]):
        done = _dammrl("sensor", *action, "--port", str(tmp_path / "nothing"))
        assert done.returncode == Exit.BAD_INPUT and "no valid frame" in done.stderr, done.stderr


def test_calibrate_command_guides_a_person_and_saves_a_file(tmp_path: Path) -> None:
    link, out = tmp_path / "ttySENSOR", tmp_path / "cal.json"
    command = [sys.executable, "-m", "dammrl", "sensor", "calibrate", "--port", str(link)]
    command += ["--out", str(out), "--seconds", "1"]
    with SensorEmulator(link, []) as pad:
        pipe = subprocess.PIPE
        person = subprocess.Popen(command, stdin=pipe, stdout=pipe, stderr=pipe, text=True)
        assert person.stdin is not None and person.stdout is not None
        for line in person.stdout:  # do what each step asks, then press Enter
            if line.startswith("Step"):
                pad.hold(HOLD_LEVELS[line.split(" - ")[1].split(":")[0]])
                person.stdin.write("\n")
                person.stdin.flush()
            if line.startswith("Saved"):
                break
        assert person.wait(30) == 0, person.stderr.read() if person.stderr else ""
    assert load_calibration(out).firm_raw > load_calibration(out).light_raw


def test_calibrate_refuses_a_pad_too_noisy_for_the_thresholds_and_says_what_to_redo(
    tmp_path: Path,
) -> None:
    link, out = tmp_path / "ttySENSOR", tmp_path / "cal.json"
    levels = {"REST": 0.0, "LIGHT": 0.5, "FIRM": 1.0}  # well apart, but noise +/-100 counts
    command = [sys.executable, "-m", "dammrl", "sensor", "calibrate", "--port", str(link)]
    command += ["--out", str(out), "--seconds", "0.5"]
    with SensorEmulator(link, [], noise_raw=100.0) as pad:
        pipe = subprocess.PIPE
        person = subprocess.Popen(command, stdin=pipe, stdout=pipe, stderr=pipe, text=True)
        assert person.stdin is not None and person.stdout is not None
        for line in person.stdout:
            if line.startswith("Step"):
                pad.hold(levels[line.split(" - ")[1].split(":")[0]])
                person.stdin.write("\n")
                person.stdin.flush()
        _, stderr = person.communicate(timeout=30)
    assert person.returncode == Exit.BAD_INPUT and not out.exists(), stderr
    assert "DAMMRL_PAD_DECODER__OFF_LEVEL" in stderr and "Redo all three steps" in stderr
    assert "Traceback" not in stderr and len(stderr.strip().splitlines()) == 1, stderr


def test_paths_that_cannot_be_used_are_clear_errors(tmp_path: Path) -> None:
    """An output in a missing directory is refused as the command line is read (exit 2,
    before any work); a device link there is bad input (exit 3)."""
    missing = tmp_path / "no" / "such"
    for args, code in (
        (["sensor", "emulate", "--link", str(missing / "tty"), "--seconds", "1"], Exit.BAD_INPUT),
        (["sensor", "calibrate", "--port", "/dev/null", "--out", str(missing / "c.json")],
         Exit.USAGE),
        (["recording", "plot", str(tmp_path / "none.mcap"), "-o", str(missing / "s2.png")],
         Exit.USAGE),
    ):  # fmt: skip
        done = _dammrl(*args)
        assert done.returncode == code and "error" in done.stderr, done.stderr
        assert len(done.stderr.strip().splitlines()[-1]) < 300 and str(missing) in done.stderr
        assert "Traceback" not in done.stderr
