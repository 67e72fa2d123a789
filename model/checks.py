"""The one field check of the settings dataclasses (the config's sections, model/ settings): each raises
SettingError naming the field, which the config loader reports as `section.field`."""

from __future__ import annotations

from admc.errors import SettingError


def require(ok: bool, key: str, problem: str, section: str | None = None) -> None:
    """Refuse `key` with `problem` unless `ok`: SettingError("key: problem"), or with `section` (a check that
    spans sections) "config key 'section.key': problem"."""
    if not ok:
        raise SettingError(key, problem, section)


def positive_ints(obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        require(
            isinstance(value, int) and not isinstance(value, bool) and value >= 1,
            name,
            f"must be an int >= 1, got {value!r}",
        )


def non_negative_ints(obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        require(
            isinstance(value, int) and not isinstance(value, bool) and value >= 0,
            name,
            f"must be an int >= 0, got {value!r}",
        )
