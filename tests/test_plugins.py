"""The plug-in seams, tried as a lab would: a package of its own (installed here as a
throwaway distribution on PYTHONPATH) brings an intent source and an arm driver, and
`dammrl up --mode real` runs an episode with them; no file of dammrl is edited."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.busutil import free_port

TOY = '''
"""A lab's own devices: a switch that always pushes toward the goal, and a first-order arm."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from pydantic_settings import SettingsConfigDict

from dammrl_core.arm.driver import DriveCommand, JointState
from dammrl_core.intent.source import Ask, Decided, Reading, SourceContext
from dammrl_core.settings import Settings
from dammrl_core.task import TaskSettings


class SwitchSettings(Settings):
    model_config = SettingsConfigDict(env_prefix="TOY_SWITCH_")
    log: Path
    delay_s: float = 0.1


class Switch:
    person = True
    waits_for_model_choice = False

    def __init__(self, settings: SwitchSettings) -> None:
        self.settings, self.asked, self.decided = settings, None, 0

    def open(self) -> None: ...
    def close(self) -> None:
        self.settings.log.write_text(f"decided {self.decided}")
    def new_episode(self, episode: int, seed: int) -> None: ...
    def ask(self, ask: Ask, now_s: float) -> None:
        self.asked = (ask, now_s)
    def cancel(self) -> None:
        self.asked = None
    def poll(self, now_s: float) -> Decided | None:
        time.sleep(0.002)
        if self.asked is None or now_s - self.asked[1] < self.settings.delay_s:
            return None
        ask, since = self.asked
        self.asked, self.decided = None, self.decided + 1
        self.settings.log.write_text(f"decided {self.decided}")
        axis = ask.primary_axis
        u_h = 1 if ask.goal_m[axis] >= ask.ee_pos_m[axis] else -1
        return Decided(u_h=u_h, human_model=ask.human_model, confidence=0.9,
                       decision_s=now_s - since)
    def readings(self) -> list[Reading]:
        return []
    def problem(self) -> str | None:
        return None
    def detail(self) -> str:
        return f"{self.decided} decisions"


class SwitchPlugin:
    name = "toy-switch"
    settings = SwitchSettings

    def create(self, settings: Settings, context: SourceContext) -> Switch:
        assert isinstance(settings, SwitchSettings)
        return Switch(settings)


class ArmSettings(Settings):
    model_config = SettingsConfigDict(env_prefix="TOY_ARM_")
    log: Path
    time_constant_s: float = 0.03
    port: str = "toy"


class FirstOrderArm:
    """Each joint follows its reference with a time constant; the torque is the law's."""

    stall_s = None

    def __init__(self, settings: ArmSettings) -> None:
        self.settings = settings
        self.q = np.array(TaskSettings().home_q_rad, dtype=float)
        self.q_ref, self.dq = self.q.copy(), np.zeros(6)
        self.last, self.commands = time.monotonic(), 0

    def connect(self, torque: bool = True, hold=None) -> bool:
        self.last = time.monotonic()
        if hold is not None:
            self.write_command(hold(self.read_state()))
        return False
    def read_state(self) -> JointState:
        now = time.monotonic()
        step = 1 - math.exp(-(now - self.last) / self.settings.time_constant_s)
        moved = (self.q_ref - self.q) * step
        self.dq = moved / max(now - self.last, 1e-6)
        self.q, self.last = self.q + moved, now
        return JointState(self.q.copy(), self.dq.copy(), np.zeros(6))
    def write_command(self, command: DriveCommand) -> None:
        self.q_ref = np.array(command.q_ref, dtype=float)
        self.commands += 1
    def torque_off(self) -> list[int]:
        return []
    def rearm(self) -> list[int]:
        return []
    def restart(self, joint: int) -> None: ...
    def joint_limits(self, robot):
        return robot.q_min, robot.q_max
    def disconnect(self) -> None:
        self.settings.log.write_text(f"commands {self.commands}")
    def __enter__(self) -> FirstOrderArm:
        self.connect()
        return self
    def __exit__(self, *exc: object) -> None:
        self.disconnect()


class ArmPlugin:
    name = "toy-arm"
    settings = ArmSettings

    def create(self, settings: Settings) -> FirstOrderArm:
        assert isinstance(settings, ArmSettings)
        return FirstOrderArm(settings)

    def scan(self, settings: Settings) -> list[str]:
        return ["one first-order arm"]

    def calibrate(self, settings, robot, limits, ask, say):
        raise NotImplementedError


SWITCH = SwitchPlugin()
ARM = ArmPlugin()
'''


@pytest.fixture
def lab_package(tmp_path: Path) -> Path:
    """A distribution ``toyplug`` on a directory of its own, as pip would install it."""
    site = tmp_path / "site"
    (site / "toyplug").mkdir(parents=True)
    (site / "toyplug" / "__init__.py").write_text(textwrap.dedent(TOY))
    info = site / "toyplug-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toyplug\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[dammrl.intent_sources]\ntoy-switch = toyplug:SWITCH\n\n"
        "[dammrl.arm_drivers]\ntoy-arm = toyplug:ARM\n"
    )
    return site


def _env(site: Path, **settings: str) -> dict[str, str]:
    path = os.pathsep.join(p for p in (str(site), os.environ.get("PYTHONPATH")) if p)
    return dict(os.environ, PYTHONPATH=path, **settings)


def _dammrl(
    env: dict[str, str], *args: str, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "dammrl", *args]
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout)


def test_a_package_lists_its_source_and_driver(lab_package: Path) -> None:
    env = _env(lab_package)
    sources = _dammrl(env, "intent", "sources")
    drivers = _dammrl(env, "robot", "drivers")
    assert sources.returncode == 0 and drivers.returncode == 0, sources.stderr + drivers.stderr
    assert "toy-switch       package toyplug" in sources.stdout.splitlines()
    assert "simulated        built-in" in sources.stdout.splitlines()
    assert "toy-arm          package toyplug" in drivers.stdout.splitlines()
    scan = _dammrl(env | {"TOY_ARM_LOG": "/dev/null"}, "robot", "scan", "--driver", "toy-arm")
    assert scan.returncode == 0 and "one first-order arm" in scan.stdout, scan.stderr


def test_an_unknown_source_is_one_line_naming_the_installed_ones(lab_package: Path) -> None:
    env = _env(lab_package, DAMMRL_INTENT_SOURCE="emg-nope", DAMMRL_ARM_DRIVER="toy-arm",
               TOY_ARM_LOG="/dev/null")  # fmt: skip
    done = _dammrl(env, "up", "--mode", "real", "--episodes", "1", "--bus-port", str(free_port()))
    assert done.returncode != 0
    error = done.stderr.strip().splitlines()
    assert (
        len(error) == 1 and "unknown intent source (DAMMRL_INTENT_SOURCE) 'emg-nope'" in error[0]
    ), done.stderr
    assert "toy-switch" in error[0] and "Traceback" not in done.stderr


@pytest.mark.slow
def test_dammrl_up_runs_an_episode_on_a_packages_source_and_driver(
    lab_package: Path, tmp_path: Path
) -> None:
    switch, arm = tmp_path / "switch.log", tmp_path / "arm.log"
    env = _env(lab_package, DAMMRL_INTENT_SOURCE="toy-switch", DAMMRL_ARM_DRIVER="toy-arm",
               TOY_SWITCH_LOG=str(switch), TOY_ARM_LOG=str(arm),
               DAMMRL_TASK_EPISODE_TIMEOUT_S="30")  # fmt: skip
    done = _dammrl(env, "up", "--mode", "real", "--episodes", "1", "--json", "--model", "1,1",
                   "--bus-port", str(free_port()), timeout=240)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    # the goal reached (success is a press of the goal's button, which this arm has not)
    assert result["reached"], result
    decided = int(switch.read_text().split()[1])
    commands = int(arm.read_text().split()[1])
    assert decided >= 3 and commands >= 100, (decided, commands, done.stderr[-2000:])
