"""Simulation settings: one class, environment prefix ``DAMMRL_SIM_``."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from dammrl.robot import DEFAULT_URDF


class DomainRandomization(BaseModel):
    """Seeded perturbations of the simulated arm (off by default)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = False
    mass_scale: float = Field(0.15, ge=0, lt=1)
    """Link masses (and inertias) scaled by U(1 - s, 1 + s)."""
    damping_scale: float = Field(0.3, ge=0, lt=1)
    """Joint damping scaled by U(1 - s, 1 + s)."""
    friction_max_nm: float = Field(0.3, ge=0)
    """Joint dry friction drawn from U(0, max) [N m]."""
    q_noise_rad: float = Field(2e-4, ge=0)
    """Standard deviation of joint-position sensor noise [rad]."""
    dq_noise_rad_per_s: float = Field(2e-3, ge=0)
    """Standard deviation of joint-velocity sensor noise [rad/s]."""
    ee_noise_m: float = Field(2e-4, ge=0)
    """Standard deviation of end-effector position noise [m]."""


class SimSettings(BaseSettings):
    """The simulated arm and its scene."""

    model_config = SettingsConfigDict(
        env_prefix="DAMMRL_SIM_", env_nested_delimiter="__", frozen=True, extra="forbid"
    )

    urdf_path: Path = DEFAULT_URDF
    """Any 6-DoF URDF; the default is the dammrl reference rehabilitation arm."""
    ee_frame: str = "fingertip"
    """URDF link whose origin is the end-effector point x."""
    armature_kgm2: tuple[float, ...] = (0.05, 0.05, 0.03, 0.03, 0.01, 0.01)
    """Reflected rotor inertia per joint [kg m^2] (no URDF tag exists for it)."""
    timestep_s: float = Field(0.001, gt=0, le=0.005)
    """Physics step [s]."""
    table_top_z_m: float = -0.25
    """Table height in the robot base frame [m] (the shoulder is the origin)."""
    button_press_travel_m: float = Field(0.003, gt=0)
    """Cap travel at which the button counts as pressed [m]."""
    randomization: DomainRandomization = DomainRandomization()
    seed: int | None = None
    """Seed of the domain randomisation and sensor noise (None: fresh entropy)."""

    # --- the node (bus) ---
    state_rate_hz: float = Field(100.0, gt=0, le=1000)
    """RobotState publication rate; also the rate at which commands are taken up [Hz]."""
    command_stale_s: float = Field(0.1, gt=0)
    """No valid command for this long: hold position (gravity compensation + damping) [s]."""
    hold_kp_nm_per_rad: float = Field(100.0, ge=0)
    """Stiffness of a hold before any command arrived (then: the last command's) [N m/rad]."""
    hold_kd_nms_per_rad: float = Field(10.0, ge=0)
    """Damping of a hold before any command arrived (then: the last command's) [N m s/rad]."""
    max_kp_nm_per_rad: float = Field(2000.0, gt=0)
    """Commands asking for more stiffness are rejected [N m/rad]."""
    max_kd_nms_per_rad: float = Field(200.0, gt=0)
    """Commands asking for more damping are rejected [N m s/rad]."""
    limit_tolerance_rad: float = Field(0.05, ge=0)
    """Commanded q_ref may exceed the joint limits by this much before rejection [rad]."""
