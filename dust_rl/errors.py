"""Errors a user can fix, and the range checks that raise them.

The ``dust-rl`` command prints a :class:`UserError` (and a few library errors of the same
kind: an unusable checkpoint's :class:`CheckpointError`, file system errors) as one line,
``dust-rl: error: <message>``; any other exception is a bug and keeps its traceback. Nothing
here imports torch or another layer of the package, so every layer raises these.
"""

from __future__ import annotations

import contextlib
import errno
import math
from collections.abc import Callable, Iterator


class UserError(Exception):
    """Bad input (an argument, a file, a folder); the message names the problem and what to do."""


class ConfigError(UserError):
    """A setting is out of range, of the wrong kind, or contradicts another setting.

    Not a ``ValueError`` on purpose: tyro reports ValueErrors raised while it builds a config
    in its own usage box; the CLI reports every user error the same way, as one line.
    """



class DatasetError(UserError, ValueError):
    """A dataset is missing, corrupt, truncated, or does not match what was asked for.

    The message names the dataset path and the problem so that a user can act on it
    (delete the folder, re-run collection, pick the right env) without a traceback hunt.
    """

def check_at_least(config: object, minimum: int, *names: str) -> None:
    """Raise :class:`ConfigError` naming the first of ``config``'s fields ``names`` below ``minimum``.

    Fields set to None (meaning "the default") pass.
    """
    for name in names:
        value = getattr(config, name)
        if value is not None and not value >= minimum:
            raise ConfigError(f"{name} must be >= {minimum}, got {value}")


def check_finite(config: object, *names: str, positive: bool = False) -> None:
    """Raise :class:`ConfigError` naming the first of ``config``'s fields ``names`` that is not finite
    (and > 0 when ``positive``, else >= 0)."""
    for name in names:
        value = getattr(config, name)
        if not (math.isfinite(value) and (value > 0 if positive else value >= 0)):
            raise ConfigError(f"{name} must be a finite number {'>' if positive else '>='} 0, got {value}")


def check_fraction(config: object, *names: str) -> None:
    """Raise :class:`ConfigError` naming the first of ``config``'s fields ``names`` outside [0, 1)."""
    for name in names:
        value = getattr(config, name)
        if not 0 <= value < 1:
            raise ConfigError(f"{name} must be in [0, 1), got {value}")


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, of another kind, or does not fit what it is loaded into."""


def one_line(err: BaseException) -> str:
    """``err`` as ``Type: message`` on one line (library messages may span several)."""
    return f"{type(err).__name__}: {' '.join(str(err).split())}"


class NoSpaceError(UserError):
    """The disk filled up while a command wrote its files."""


@contextlib.contextmanager
def no_space_left(doing: str, advice: str, clean: Callable[[], None] | None = None) -> Iterator[None]:
    """Turn a full disk (``OSError`` ENOSPC) in the ``with`` body into :class:`NoSpaceError` saying so, after
    ``clean`` removed what was half written; any other error passes unchanged."""
    try:
        yield
    except OSError as err:
        if err.errno != errno.ENOSPC:
            raise
        if clean is not None:
            clean()
        raise NoSpaceError(f"no space left on device while {doing} ({err.filename or err.strerror}); {advice}") from err
