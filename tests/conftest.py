# ruff: noqa: E402  (headless_gl must run before MuJoCo is first imported)
"""Shared fixtures: the reference arm and its models, built once per test session."""

from __future__ import annotations

import numpy as np
import pytest

from dammrl.cli.common import headless_gl

headless_gl()  # before MuJoCo is imported: the video tests render offscreen

from dammrl.stack.runner import ReachRunner
from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotDescription
from dammrl_core.robot.scene import SceneLayout
from dammrl_core.sim.settings import SimSettings
from dammrl_core.sim.simulation import Simulation

HOME_Q = np.array([0.0, 1.0, 0.0, 1.6, 0.0, 0.3])


@pytest.fixture(scope="session")
def robot() -> RobotDescription:
    return RobotDescription.from_urdf()


@pytest.fixture(scope="session")
def arm(robot: RobotDescription) -> ArmModel:
    return ArmModel(robot)


@pytest.fixture()
def sim(robot: RobotDescription) -> Simulation:
    return Simulation(SimSettings(), robot, SceneLayout())


@pytest.fixture(scope="session")
def runner() -> ReachRunner:
    return ReachRunner()


def random_postures(robot: RobotDescription, n: int, seed: int, spread: float = 0.4) -> np.ndarray:
    """``n`` postures around home, inside the joint limits, shape (n, 6)."""
    rng = np.random.default_rng(seed)
    q = HOME_Q + rng.uniform(-spread, spread, (n, 6))
    return np.clip(q, robot.q_min + 0.05, robot.q_max - 0.05)
