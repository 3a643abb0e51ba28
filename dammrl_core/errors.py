"""One exception hierarchy for the whole project.

Messages name the bad value and what was expected, so a researcher can fix a setting
without reading the code.
"""

from enum import IntEnum


class Exit(IntEnum):
    """Exit codes of every ``dammrl`` command (and ``python -m services.<name>``)."""

    OK = 0
    FAILED = 1
    """The job could not be carried out: a service died, nothing answered or was found
    (a reach that misses its goal is a result, not a failure)."""
    USAGE = 2
    """The command line is wrong (argparse's own code)."""
    BAD_INPUT = 3
    """A setting (flag or DAMMRL_* variable), a file or a device cannot be used: one line
    names it and says what was expected."""
    INTERRUPTED = 130
    """Ctrl-C (SIGINT) or SIGTERM before a finite job ended; open-ended commands (``echo``,
    ``replay --loop``, ``up`` without ``--episodes``) end with OK."""


class DammrlError(Exception):
    """Base class of every error raised on purpose by dammrl."""

    exit_code: Exit = Exit.BAD_INPUT
    """How a command that ends on this error exits."""


class JobFailedError(DammrlError):
    """The job could not be carried out (a service died, nothing answered)."""

    exit_code = Exit.FAILED


class RobotDescriptionError(DammrlError):
    """The URDF cannot serve as a 6-DoF arm (missing frame, wrong joint count, ...)."""


class ConfigurationError(DammrlError, ValueError):
    """A setting is outside its documented range."""


class UsageError(DammrlError):
    """Options that cannot go together (exits like a bad command line)."""

    exit_code = Exit.USAGE


class IKError(DammrlError):
    """Inverse kinematics found no acceptable joint configuration for a target."""


EXIT_CODES_HELP = (
    "exit codes: 0 ok, 1 the job could not be done (a service died, nothing answered), "
    "2 bad command line, 3 a setting, file or device cannot be used, 130 interrupted"
)
