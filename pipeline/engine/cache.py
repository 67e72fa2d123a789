"""The task cache: every task's output is a folder root/<stage>/<key>, published atomically.

A task's key hashes its stage, parameters, its inputs' keys and the version of its code, so a
changed parameter, upstream output or stage implementation gives a new key (and the old output
stays valid for the old inputs). A task runs in root/.tmp/<key>.<host>.<pid>.<uuid>/ and is renamed
into place only after its `_task.json` manifest is written: an interrupted run never leaves a
folder that looks done, and the next run resumes with the unfinished tasks.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import hashlib
import inspect
import os
import re
import shutil
import socket
import time
import types
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from admc.errors import AdmcError
import admc
from admc.stores.atomic import JsonFileError, dumps_canonical, fsync_path, read_json, write_json

MANIFEST = "_task.json"
TMP_DIR = ".tmp"
KEY_LENGTH = 20
STAGE_NAME = re.compile(r"^[a-z][a-z0-9_-]*$")
# A temporary folder of another machine sharing the cache counts as stale only after this long.
FOREIGN_TMP_MAX_AGE_S = 24 * 3600


class TaskError(AdmcError, RuntimeError):
    """A task's function failed; the message names the task so a failed run says what to look at."""


def code_version(*objs: Any) -> str:
    """Hash of the source files behind modules/functions/classes (whole packages for packages) + admc's version.

    Editing any of those files changes the version, hence the keys of the tasks built with it.
    """
    if not objs:
        raise ValueError("code_version needs at least one module, function or class")
    digests = set()
    for obj in objs:
        for path in _source_files(obj):
            digests.add(hashlib.sha256(path.read_bytes()).hexdigest())
    payload = dumps_canonical({"admc": admc.__version__, "sources": sorted(digests)})
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _source_files(obj: Any) -> list[Path]:
    if isinstance(obj, types.ModuleType) and hasattr(obj, "__path__"):  # a package: all of it
        return sorted(p for folder in obj.__path__ for p in Path(folder).rglob("*.py"))
    try:
        source = inspect.getsourcefile(obj)
    except TypeError:
        source = None
    if source is None or not os.path.isfile(source):
        raise ValueError(f"code_version: no Python source file for {obj!r}")
    return [Path(source)]


@dataclasses.dataclass(frozen=True, eq=False)
class Task:
    """One cached unit of work: fn(out_dir, inputs, **params) writes into out_dir and returns a JSON summary.

    `inputs` maps a name to an upstream Task; fn receives the same names mapped to their published
    folders. `code_version` defaults to code_version(fn). `source` names what the task works on as
    its user knows it (a scene file), so a failure report can point there; it is not part of the key.
    """

    stage: str
    label: str
    fn: Callable[..., dict | None]
    params: dict = dataclasses.field(default_factory=dict)
    inputs: dict[str, Task] = dataclasses.field(default_factory=dict)
    code_version: str = ""
    source: str = ""

    def __post_init__(self) -> None:
        if not STAGE_NAME.match(self.stage):
            raise ValueError(f"task {self.label!r}: stage {self.stage!r} must match {STAGE_NAME.pattern}")
        for name, upstream in self.inputs.items():
            if not isinstance(upstream, Task):
                raise TypeError(f"task {self.label!r}: input {name!r} is a {type(upstream).__name__}, not a Task")
        try:
            dumps_canonical(self.params)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"task {self.label!r}: params must be JSON-able and finite ({exc})") from None
        if not self.code_version:
            object.__setattr__(self, "code_version", code_version(self.fn))

    @functools.cached_property
    def key(self) -> str:
        """sha256 of stage, canonical params, inputs' keys and code version (stable across processes)."""
        payload = dumps_canonical(
            {
                "stage": self.stage,
                "params": self.params,
                "code_version": self.code_version,
                "inputs": {name: upstream.key for name, upstream in self.inputs.items()},
            }
        )
        return hashlib.sha256(payload.encode()).hexdigest()[:KEY_LENGTH]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Task) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)


class TaskCache:
    """Published task outputs under root/<stage>/<key>/, each with a `_task.json` manifest written last."""

    def __init__(self, root: Path):
        self.root = Path(root)

    @property
    def tmp_root(self) -> Path:
        return self.root / TMP_DIR

    def path(self, task_or_key: Task | str) -> Path:
        """Where a task's output is (or will be) published; a bare key is looked up among the stages."""
        if isinstance(task_or_key, Task):
            return self.root / task_or_key.stage / task_or_key.key
        found = [p for p in self._stage_dirs() if (p / task_or_key).is_dir()]
        if not found:
            raise KeyError(f"{self.root}: no cached entry with key {task_or_key!r}")
        return found[0] / task_or_key

    def is_done(self, task: Task) -> bool:
        """Published and intact: a damaged entry (a file deleted or truncated since) counts as not done, so the
        task runs again and its new output replaces the entry, instead of failing downstream on every run."""
        folder = self.path(task)
        return (folder / MANIFEST).is_file() and _intact(folder)

    def manifest(self, task: Task) -> dict:
        if not self.is_done(task):
            raise KeyError(f"{self.root}: task {task.label!r} ({task.stage}/{task.key}) is not cached")
        return read_json(self.path(task) / MANIFEST)

    def summary(self, task: Task) -> dict | None:
        """The JSON summary the task's function returned."""
        return self.manifest(task)["summary"]

    def run_task(self, task: Task, input_paths: dict[str, Path]) -> Path:
        """Run `task` unless it is published; publish its output atomically and return the folder."""
        final = self.path(task)
        if self.is_done(task):
            return final
        missing = set(task.inputs) - set(input_paths)
        if missing:
            raise TaskError(f"task {task.label!r}: no path given for input(s) {sorted(missing)}")
        self.tmp_root.mkdir(parents=True, exist_ok=True)
        work = self.tmp_root / f"{task.key}.{_host_id()}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        work.mkdir()
        start = time.perf_counter()
        try:
            summary = task.fn(work, {name: Path(p) for name, p in input_paths.items()}, **task.params)
            write_json(
                work / MANIFEST,
                {
                    "files": {
                        str(f.relative_to(work)): f.stat().st_size for f in sorted(work.rglob("*")) if f.is_file()
                    },
                    "stage": task.stage,
                    "label": task.label,
                    "key": task.key,
                    "params": task.params,
                    "inputs": {name: upstream.key for name, upstream in task.inputs.items()},
                    "code_version": task.code_version,
                    "summary": summary,
                    "seconds": round(time.perf_counter() - start, 4),
                    "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                },
            )
        except Exception as exc:
            shutil.rmtree(work, ignore_errors=True)
            raise TaskError(
                f"{task.stage} task {task.label!r} (key {task.key}) failed: {type(exc).__name__}: {exc}"
            ) from exc
        except BaseException:
            shutil.rmtree(work, ignore_errors=True)
            raise
        self._publish(task, work, final)
        return final

    def _publish(self, task: Task, work: Path, final: Path) -> None:
        final.parent.mkdir(parents=True, exist_ok=True)
        if final.exists() and not self.is_done(task):
            self._discard(final)  # not ours and never completed: nothing of ours publishes without a manifest
        try:
            os.rename(work, final)
        except OSError:
            if not self.is_done(task):
                shutil.rmtree(work, ignore_errors=True)
                raise
            shutil.rmtree(work, ignore_errors=True)  # another worker published the same key first
            return
        fsync_path(final.parent)

    def _discard(self, folder: Path) -> None:
        """Move a folder out of sight first (one rename), then delete it: never a half-deleted entry."""
        self.tmp_root.mkdir(parents=True, exist_ok=True)
        trash = self.tmp_root / f"deleted.{uuid.uuid4().hex}"
        os.rename(folder, trash)
        shutil.rmtree(trash, ignore_errors=True)

    def _stage_dirs(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        return sorted(p for p in self.root.iterdir() if p.is_dir() and p.name != TMP_DIR)

    def _published(self, stage: str | None = None) -> list[Path]:
        return [
            entry
            for folder in self._stage_dirs()
            if stage is None or folder.name == stage
            for entry in sorted(folder.iterdir())
            if (entry / MANIFEST).is_file()
        ]

    def entries(self) -> list[dict]:
        """Every published task: stage, label, key, bytes on disk, seconds it ran, created (UTC ISO time)."""
        out = []
        for entry in self._published():
            manifest = read_json(entry / MANIFEST)
            size = sum(f.stat().st_size for f in entry.rglob("*") if f.is_file())
            out.append(
                {
                    "stage": manifest["stage"],
                    "label": manifest["label"],
                    "key": manifest["key"],
                    "bytes": size,
                    "seconds": manifest["seconds"],
                    "created": manifest["created"],
                    "path": entry,
                }
            )
        return sorted(out, key=lambda e: (e["created"], e["stage"], e["key"]))

    def clear(self, stage: str | None = None) -> int:
        """Remove published entries (all, or one stage's) and stale temporary folders; count the entries."""
        entries = self._published(stage)
        for entry in entries:
            self._discard(entry)
        self.clean_stale_tmp()
        return len(entries)

    def forget(self, task: Task) -> bool:
        """Drop one published entry (its output went missing elsewhere, e.g. a deleted patch store)."""
        if not self.is_done(task):
            return False
        self._discard(self.path(task))
        return True

    def clean_stale_tmp(self) -> int:
        """Remove temporary folders left by killed runs; those of live processes stay. Returns the count."""
        if not self.tmp_root.is_dir():
            return 0
        removed = 0
        for folder in self.tmp_root.iterdir():
            if _is_stale(folder):
                shutil.rmtree(folder, ignore_errors=True)
                removed += 1
        return removed


def _intact(folder: Path) -> bool:
    """Whether every file the manifest lists is there with its size as published (a readable manifest
    without that list predates it and is trusted)."""
    try:
        files = read_json(folder / MANIFEST).get("files", {})
    except (JsonFileError, FileNotFoundError, AttributeError):
        return False
    for name, size in files.items():
        try:
            if (folder / name).stat().st_size != size:
                return False
        except FileNotFoundError:
            return False
    return True


@functools.cache
def _host_id() -> str:
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def _is_stale(folder: Path) -> bool:
    """A temp folder is stale when its process is gone (same host) or it is old (another host)."""
    parts = folder.name.split(".")
    if parts[0] == "deleted":
        return True
    if len(parts) != 4 or not parts[2].isdigit():
        return True  # not a name this cache writes
    _key, host, pid, _ = parts
    if host != _host_id():
        return time.time() - folder.stat().st_mtime > FOREIGN_TMP_MAX_AGE_S
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # a live process of another user
    return False
