"""Run a graph of cached Tasks on dask: in process, on threads, on a local process cluster or any scheduler.

Tasks already published are not scheduled at all. The rest become one dask node each that calls
`TaskCache.run_task` with its inputs' published folders. A failing task does not stop the others:
independent tasks finish and publish, dependents of the failed one are skipped, and the run then
raises one TaskError listing every failed task (what it works on, the cause in one line), so the
next run resumes with only what is left.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import socket
import traceback
from pathlib import Path

import dask
from dask.callbacks import Callback
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from admc.errors import AdmcError
from admc.pipeline.engine.cache import Task, TaskCache, TaskError

LOCAL_SCHEDULERS = ("sync", "threads")
PROBE_TIMEOUT_S = 5.0  # for the first TCP connect only; a scheduler that answers keeps dask's own timeouts


class SchedulerError(AdmcError, ConnectionError):
    """run.scheduler names a dask scheduler that cannot be reached."""


@dataclasses.dataclass
class _Failed:
    """A node's outcome when its task (or an upstream task) failed; travels between processes."""

    label: str
    message: str
    detail: str = ""  # the original traceback, formatted where it happened


def default_workers(cores: int | None = None) -> int:
    """Process workers for a local cluster: 1 on <= 2 cores, else cores // 4.

    A Mitsuba JIT render already uses every core of its process, so several renders per machine
    only oversubscribe the CPU; a few workers still overlap one task's Python/EXR/Zarr work with
    another's rendering. Each worker runs one task at a time (threads_per_worker=1).
    """
    cores = cores or len(os.sched_getaffinity(0))
    return 1 if cores <= 2 else max(1, cores // 4)


def collect(tasks: list[Task]) -> dict[str, Task]:
    """Every task and its upstream tasks, deduplicated by key, upstream before downstream."""
    ordered: dict[str, Task] = {}
    for root in tasks:
        stack = [(root, False)]
        while stack:
            task, expanded = stack.pop()
            if task.key in ordered:
                continue
            if expanded:
                ordered[task.key] = task
            else:
                stack.append((task, True))
                stack.extend((upstream, False) for upstream in task.inputs.values() if upstream.key not in ordered)
    return ordered


def run(
    tasks: list[Task], cache: TaskCache, *, scheduler: str = "sync", workers: int | None = None, progress: bool = True
) -> dict[str, Path]:
    """Publish every task and its upstream tasks; return key -> published folder.

    scheduler: "sync" (in process, one at a time), "threads", "processes" (a local dask.distributed
    cluster of `workers` single-threaded processes, default `default_workers()`), or the address of
    a running dask.distributed scheduler.
    """
    graph = collect(tasks)
    cache.clean_stale_tmp()
    published = {key: cache.path(task) for key, task in graph.items() if cache.is_done(task)}
    pending = [task for key, task in graph.items() if key not in published]
    if not pending:
        return published
    if scheduler not in (*LOCAL_SCHEDULERS, "processes"):
        _probe(scheduler)  # before the bar: an unreachable scheduler is one message, not a bar stuck at 0
    with _Bar(total=len(graph), done=len(published), enabled=progress) as bar:
        if scheduler in LOCAL_SCHEDULERS:
            outcomes = _run_local(pending, published, cache, scheduler, workers, bar)
        else:
            outcomes = _run_distributed(pending, published, cache, scheduler, workers, bar)
    published.update({key: out for key, out in outcomes.items() if isinstance(out, Path)})
    failed = [out for out in outcomes.values() if isinstance(out, _Failed) and out.detail]
    skipped = sum(isinstance(out, _Failed) and not out.detail for out in outcomes.values())
    if failed:
        lines = [
            f"{len(failed)} task(s) failed, {skipped} skipped for lack of their inputs; "
            f"{len(published)} of {len(graph)} are published and stay cached (fix the cause and rerun: "
            "only the rest runs):",
            *(f"  {out.message}" for out in failed),
        ]
        error = TaskError("\n".join(lines))
        for out in failed:
            error.add_note(out.detail)
        raise error
    return published


def _node_name(task: Task) -> str:
    return f"{task.stage}-{task.key}"


def _run_node(cache: TaskCache, task: Task, inputs: dict[str, Path | _Failed]) -> Path | _Failed:
    """One dask node: run the task unless an input failed; failures come back as values (keep going)."""
    lost = [name for name, value in inputs.items() if isinstance(value, _Failed)]
    if lost:
        return _Failed(task.label, f"{task.stage} task {task.label!r} skipped: input(s) {', '.join(lost)} failed")
    try:
        return cache.run_task(task, inputs)
    except TaskError as exc:
        return _Failed(task.label, _failure_line(task, exc), "".join(traceback.format_exception(exc)))


def _failure_line(task: Task, error: TaskError) -> str:
    """'<stage> <label> (<source>): <cause>' on one line; a user error's own message needs no type name."""
    cause = error.__cause__ or error
    text = str(cause) if isinstance(cause, AdmcError) else f"{type(cause).__name__}: {cause}"
    where = ""
    if task.source and task.source not in task.label:
        text = text.removeprefix(f"{task.source}: ")  # a scene error starts with the file it is about
        where = f" ({task.source})"
    return f"{task.stage} {task.label!r}{where}: {' '.join(text.split())}"


def _inputs_of(task: Task, published: dict[str, Path], nodes: dict) -> dict:
    return {name: published[up.key] if up.key in published else nodes[up.key] for name, up in task.inputs.items()}


def _run_local(pending, published, cache, scheduler, workers, bar) -> dict[str, Path | _Failed]:
    nodes = {}
    for task in pending:
        node = dask.delayed(functools.partial(_run_node, cache, task), pure=False)
        nodes[task.key] = node(_inputs_of(task, published, nodes), dask_key_name=_node_name(task))
    labels = {_node_name(task): task.label for task in pending}
    callback = Callback(
        pretask=lambda key, dsk, state: bar.running(labels[key]),
        posttask=lambda key, result, dsk, state, worker: bar.finished(labels[key], result),
    )
    options = {"num_workers": workers} if scheduler == "threads" and workers else {}
    with callback:
        results = dask.compute(*nodes.values(), scheduler=scheduler, **options)
    return dict(zip(nodes, results))


def _run_distributed(pending, published, cache, scheduler, workers, bar) -> dict[str, Path | _Failed]:
    from distributed import Client, LocalCluster, as_completed

    if scheduler == "processes":
        cluster = LocalCluster(
            n_workers=workers or default_workers(),
            threads_per_worker=1,
            processes=True,
            # CRITICAL: a task's failure comes back as its value; what the workers log at
            # shutdown (a heartbeat racing the closing scheduler) is noise after a good run
            dashboard_address=None,
            silence_logs=logging.CRITICAL,
        )
        client = Client(cluster)
    else:
        try:
            cluster, client = None, Client(scheduler)
        except OSError as error:  # something answers there, but not as a dask scheduler
            raise SchedulerError(
                f"could not connect to the dask scheduler at {scheduler} (run.scheduler): {error}"
            ) from error
    try:
        futures = {}
        for task in pending:
            futures[task.key] = client.submit(
                functools.partial(_run_node, cache, task),
                _inputs_of(task, published, futures),
                key=_node_name(task),
                pure=False,
            )
        label_of = {future.key: task.label for future, task in zip(futures.values(), pending)}
        bar.running(f"{len(pending)} task(s) on {scheduler}")
        for future in as_completed(list(futures.values())):
            bar.finished(label_of[future.key], future.result())
        return {key: future.result() for key, future in futures.items()}
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _probe(address: str) -> None:
    """SchedulerError (naming the address) when it is no scheduler address or nothing listens there.

    A TCP address gets a short connect first: dask itself retries for its 30 s connect timeout and
    then raises a bare OSError. Other protocols (ucx, inproc) are left to dask.
    """
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme not in ("tcp", "tls"):
            return
        host, port = parse_host_port(location)
    except ValueError as error:
        raise SchedulerError(
            f"run.scheduler = {address!r} is not sync, threads, processes or a dask scheduler "
            f"address such as tcp://host:8786 ({error})"
        ) from None
    try:
        socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S).close()
    except OSError as error:
        raise SchedulerError(
            f"no dask scheduler answers at {address} (run.scheduler): {error}. Start one "
            "(`dask scheduler`) or use run.scheduler = processes, threads or sync"
        ) from None


class _Bar:
    """A rich progress bar on stderr (tasks done / total, current label); silent when disabled."""

    def __init__(self, total: int, done: int, enabled: bool):
        self.enabled = enabled
        self.failed = self.skipped = 0
        self.progress = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            disable=not enabled,
        )
        self.bar = self.progress.add_task("starting", total=total, completed=done)

    def __enter__(self) -> _Bar:
        self.progress.start()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.stop()

    def running(self, label: str) -> None:
        self.progress.update(self.bar, description=f"running {label}")

    def finished(self, label: str, outcome: Path | _Failed) -> None:
        if isinstance(outcome, _Failed):
            self.failed += bool(outcome.detail)
            self.skipped += not outcome.detail
            if self.enabled:
                self.progress.console.print(f"[red]{escape(outcome.message)}[/]")  # Mitsuba's [file.cpp:N]
        trouble = f" ({self.failed} failed, {self.skipped} skipped)" if self.failed or self.skipped else ""
        self.progress.update(self.bar, advance=1, description=f"done {label}{trouble}")
        if self.enabled and not self.progress.console.is_terminal:
            # a live bar draws nothing into a log file or CI output: one plain line per task instead
            task = self.progress.tasks[0]
            self.progress.console.print(
                f"[{int(task.completed)}/{int(task.total)}] done {label}{trouble}", markup=False, highlight=False
            )
