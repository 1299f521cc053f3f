"""The errors a user can act on. The command line prints them on one line and exits 2; they
are ValueErrors (or OSErrors), so library callers can catch them as the built-in kinds."""

from __future__ import annotations


class UserError(ValueError):
    """A mistake in what the user gave (arguments, config, files): the CLI prints the message
    on one line and exits 2. A ValueError, so library callers can catch it as one."""


class ConfigTypeError(UserError, TypeError):
    """A config value of the wrong type (the message names the key, the value and the type)."""


class DamagedFileError(UserError):
    """A file that cannot be what was written: its checksum does not match, or its rows are cut
    short (the message says how to recover)."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, carrying what a command's user should do to continue (its ``args[0]``)."""


class RunExists(FileExistsError):
    """The output directory holds a finished run, or an unfinished one without ``--resume``."""
