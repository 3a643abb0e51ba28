"""One exception hierarchy for the whole project.

Messages name the bad value and what was expected, so a researcher can fix a setting
without reading the code.
"""


class DammrlError(Exception):
    """Base class of every error raised on purpose by dammrl."""


class RobotDescriptionError(DammrlError):
    """The URDF cannot serve as a 6-DoF arm (missing frame, wrong joint count, ...)."""


class ConfigurationError(DammrlError, ValueError):
    """A setting is outside its documented range."""


class IKError(DammrlError):
    """Inverse kinematics found no acceptable joint configuration for a target."""
