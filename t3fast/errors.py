"""The errors a user can cause and fix: bad data, configs, checkpoints and arguments.

Every one is a ``ValueError`` so library callers can catch them as such. The ``t3fast``
command prints these (and :data:`EXPECTED_ERRORS`) as one line ``t3fast <command>: <message>``
and exits non-zero; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class T3fastError(ValueError):
    """Base of the errors the user can fix; the message says what is wrong and where."""


class DataFormatError(T3fastError):
    """A data file (info pickle, labels, poses) is missing, malformed or unsafe."""


class ConfigError(T3fastError):
    """A configuration file, preset name or override is invalid."""


class CheckpointError(T3fastError):
    """A checkpoint is unreadable or of the wrong kind for the command."""


class UsageError(T3fastError):
    """A command-line argument is out of range or contradicts another."""


class DivergenceError(T3fastError):
    """Training cannot go on: its loss or its weights are no longer finite numbers."""


#: Raised by user input rather than by bugs; the CLI reports them in one line.
#: OSError covers missing files, permissions, a file where a folder is needed, a full disk.
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError)
