"""The one exception type for unusable datasets."""

from __future__ import annotations

from dust_rl.errors import UserError


class DatasetError(UserError, ValueError):
    """A dataset is missing, corrupt, truncated, or does not match what was asked for.

    The message names the dataset path and the problem so that a user can act on it
    (delete the folder, re-run collection, pick the right env) without a traceback hunt.
    """
