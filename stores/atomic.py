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

from admc.errors import AdmcError


class JsonFileError(AdmcError, ValueError):
    """A JSON file admc wrote (a cache manifest) is malformed: damaged or edited by hand."""


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
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_sibling(path)
    try:
        yield tmp
        if not tmp.is_file():
            raise FileNotFoundError(f"{path}: the writer produced no file at {tmp}")
        fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_path(path.parent)


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
