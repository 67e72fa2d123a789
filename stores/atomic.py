"""Publish files and folders atomically: write under a temporary sibling name, fsync, rename last.

A reader (or a resumed run) therefore sees either the old state or the complete new one, never
a half-written file, even if the writer is killed with SIGKILL or the machine loses power.
"""

from __future__ import annotations

import contextlib
import json
import os
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from admc.errors import USER_ERRNOS, AdmcError


class JsonFileError(AdmcError, ValueError):
    """A JSON file admc wrote (a cache manifest) is malformed: damaged or edited by hand."""


class WriteError(AdmcError, OSError):
    """The file system refused a write (read-only folder, full disk, no permission): the user can fix that."""


def _os_cause(exc: BaseException) -> OSError | None:
    """The OSError behind a failure, if any: libraries (torch, OpenEXR) writing to a Python file object
    re-raise its OSError as their own RuntimeError, which keeps the OSError as its context."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, OSError):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def temp_sibling(path: Path) -> Path:
    """A unique hidden name in the same folder (same filesystem, so the final rename is atomic)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")


def fsync_path(path: Path) -> None:
    """Flush a file's or a folder's entry to disk (a folder fsync makes a rename inside it durable)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def publishing(path: Path) -> Iterator[Path]:
    """Yield a temporary sibling path to write; on success fsync it and rename it onto `path`.

    On an exception the temporary file is removed and the exception propagates; `path` is untouched.
    A write the file system refused (an OSError of USER_ERRNOS, or a library's error raised from one: write
    through a Python file object so that it is) becomes one WriteError naming `path`.
    """
    path = Path(path)
    tmp = temp_sibling(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        if not tmp.is_file():
            raise RuntimeError(f"{path}: the writer produced no file at {tmp}")
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        cause = _os_cause(exc)
        refused = cause is not None and cause.errno in USER_ERRNOS
        if not refused or isinstance(exc, AdmcError) or not isinstance(exc, Exception):
            raise
        raise WriteError(f"{path}: cannot be written ({cause.strerror or cause})") from exc


def dumps_canonical(obj: Any) -> str:
    """One JSON spelling per value (sorted keys, no spaces, no NaN): safe to hash across processes."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def write_json(path: Path, obj: Any) -> None:
    """Write `obj` as indented JSON, atomically."""
    text = json.dumps(obj, indent=2, sort_keys=True, allow_nan=False) + "\n"
    with publishing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def read_json(path: Path) -> Any:
    """Parse a JSON file; a missing file raises FileNotFoundError, a malformed one JsonFileError, naming it."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise JsonFileError(f"{path}: not valid JSON ({exc})") from None
