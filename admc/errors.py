"""The one base class of every failure a user can fix (bad input, config, files, an unreachable scheduler).

The CLI catches AdmcError and prints its message: it names the file or key and the problem. Anything
else is a bug and keeps its traceback. Subclasses also derive from the built-in type they replaced
(ValueError, RuntimeError), so callers that caught those keep working.
"""

from __future__ import annotations

import errno


class AdmcError(Exception):
    """A user-fixable failure; str(error) is the whole message a user sees."""


class ConfigError(AdmcError, ValueError):
    """A config file, section, key or value admc refuses; the message names it."""


class SettingError(ConfigError):
    """One setting's value is refused (checks.require). A settings dataclass names its own field
    ("channels: must be ..."); the config loader, which knows the section, names the key in full
    ("config key 'model.channels': must be ...") with `in_section`."""

    def __init__(self, key: str, problem: str, section: str | None = None) -> None:
        self.key, self.problem, self.section = key, problem, section
        super().__init__(f"config key '{section}.{key}': {problem}" if section else f"{key}: {problem}")

    def in_section(self, section: str) -> "SettingError":
        return SettingError(self.key, self.problem, section)


class StageError(AdmcError, RuntimeError):
    """A stage cannot run as asked (e.g. tiling renders that do not exist yet, no weights to evaluate)."""


class TrainingError(AdmcError, ValueError):
    """Training cannot start or resume as asked (settings, checkpoint or data do not fit)."""


class DeviceError(AdmcError, ValueError):
    """The asked-for torch device is not one admc runs on, or this machine does not have it."""


# What the file system says when it refuses a write: the user frees space, or picks a folder they may write.
USER_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM})


def user_os_error(exc: OSError) -> str | None:
    """The one line for an OSError a user can fix (a read-only folder, a full disk), naming its file;
    None for any other OSError (a missing file admc should have checked for is a bug)."""
    if exc.errno not in USER_ERRNOS:
        return None
    return f"{exc.filename}: {exc.strerror}" if exc.filename else f"{exc.strerror}"
