"""Errors a user can cause and fix; the CLI prints them without a traceback."""

from __future__ import annotations


class UserError(Exception):
    """A problem with the user's input, named so they can fix it.

    ``exit_code`` follows the CLI's convention: 2 for a bad configuration or
    command line, 3 for unusable input data.
    """

    exit_code = 3


class ConfigError(UserError):
    """A configuration key is unknown, of the wrong type or out of range."""

    exit_code = 2


class SourceError(UserError):
    """A frame source cannot be opened or read (missing, unreadable, wrong shape)."""

    exit_code = 3


class UsageError(UserError):
    """A command-line option out of range."""

    exit_code = 2
