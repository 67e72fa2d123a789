"""Task cache and dask runner: real tasks writing real files, interrupted and resumed.

Task functions are module-level so the process scheduler can pickle them. Every call appends a
file to a log folder outside the cache, so a test can count exactly which tasks ran.
"""

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from admc.pipeline.engine.cache import Task, TaskCache, TaskError, code_version
from admc.pipeline.engine.runner import collect, default_workers, run

TESTS_DIR = Path(__file__).parent


def add_values(out_dir: Path, inputs: dict, *, name: str, value: float, log: str) -> dict:
    """value + the upstream totals; fails or hangs when the test leaves a marker file for `name`."""
    log = Path(log)
    (log / f"call.{name}.{uuid.uuid4().hex}").touch()
    if (log / f"fail-{name}").exists():
        raise RuntimeError(f"told to fail {name}")
    (out_dir / "partial.txt").write_text("half done")
    if (log / f"slow-{name}").exists():
        (log / f"started-{name}").touch()
        time.sleep(120)
    total = value + sum(float((path / "total.txt").read_text()) for path in inputs.values())
    (out_dir / "total.txt").write_text(repr(total))
    return {"total": total}


def calls(log: Path) -> list[str]:
    return sorted(p.name.split(".")[1] for p in log.glob("call.*"))


def graph(log: Path) -> dict[str, Task]:
    """a, b, e independent; c = a + b; d = c + a (a diamond plus a loose task, two stages)."""

    def task(stage, name, value, **inputs):
        return Task(
            stage=stage,
            label=f"{name} task",
            fn=add_values,
            params={"name": name, "value": value, "log": str(log)},
            inputs=inputs,
        )

    a, b, e = task("alpha", "a", 1.0), task("alpha", "b", 2.0), task("alpha", "e", 5.0)
    c = task("beta", "c", 10.0, x=a, y=b)
    d = task("beta", "d", 100.0, up=c, a=a)
    return {"a": a, "b": b, "c": c, "d": d, "e": e}


def run_graph(cache_root: str, log: str, scheduler: str = "sync", workers=None) -> dict:
    """Entry point for the subprocess tests."""
    tasks = graph(Path(log))
    return run(
        [tasks["d"], tasks["e"]], TaskCache(Path(cache_root)), scheduler=scheduler, workers=workers, progress=False
    )


@pytest.fixture
def log(tmp_path) -> Path:
    folder = tmp_path / "log"
    folder.mkdir()
    return folder


def totals(published: dict, tasks: dict) -> dict:
    return {name: float((published[t.key] / "total.txt").read_text()) for name, t in tasks.items()}


def tmp_leftovers(cache: TaskCache) -> list[str]:
    return sorted(p.name for p in cache.tmp_root.iterdir()) if cache.tmp_root.exists() else []


# --- keys -------------------------------------------------------------------------------------------


def test_key_is_stable_and_depends_on_params_inputs_and_code(log):
    tasks, again = graph(log), graph(log)
    assert {n: t.key for n, t in tasks.items()} == {n: t.key for n, t in again.items()}
    assert len({t.key for t in tasks.values()}) == 5 and len(tasks["a"].key) == 20
    a = tasks["a"]
    reordered = Task("alpha", "other label", add_values, params=dict(reversed(list(a.params.items()))))
    assert reordered.key == a.key  # label and dict order are not part of the key
    assert Task("alpha", "a", add_values, params={**a.params, "value": 1.5}).key != a.key
    assert Task("gamma", "a", add_values, params=a.params).key != a.key
    assert Task("alpha", "a", add_values, params=a.params, code_version="v2").key != a.key
    c = tasks["c"]
    other_a = Task("alpha", "a", add_values, params={**a.params, "value": 7.0})
    assert Task("beta", "c", add_values, params=c.params, inputs={"x": other_a, "y": tasks["b"]}).key != c.key
    assert Task("beta", "c", add_values, params=c.params, inputs={"z": a, "y": tasks["b"]}).key != c.key
    assert a.code_version == code_version(add_values) == code_version(sys.modules[__name__])


def test_key_is_the_same_in_another_process(log):
    script = (
        "import sys; from pathlib import Path; import test_cache_runner as t; "
        f"print(' '.join(x.key for x in t.graph(Path({str(log)!r})).values()))"
    )
    env = {**os.environ, "PYTHONPATH": str(TESTS_DIR), "PYTHONHASHSEED": "123"}
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == [t.key for t in graph(log).values()]


def test_code_version_follows_the_source_file(tmp_path, monkeypatch):
    module_file = tmp_path / "stage_impl.py"
    module_file.write_text("def body():\n    return 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import stage_impl

    before = code_version(stage_impl.body)
    assert code_version(stage_impl) == before
    module_file.write_text("def body():\n    return 2\n")
    assert code_version(stage_impl.body) != before
    with pytest.raises(ValueError, match="no Python source file"):
        code_version(len)


def test_task_validation(log):
    with pytest.raises(ValueError, match="stage 'Bad Stage'"):
        Task("Bad Stage", "x", add_values)
    with pytest.raises(ValueError, match="task 'x': params must be JSON-able"):
        Task("alpha", "x", add_values, params={"path": Path("/tmp")})
    with pytest.raises(ValueError, match="JSON-able and finite"):
        Task("alpha", "x", add_values, params={"v": float("nan")})
    with pytest.raises(TypeError, match="input 'up' is a str"):
        Task("alpha", "x", add_values, inputs={"up": "a"})


def test_collect_dedupes_and_orders_upstream_first(log):
    tasks = graph(log)
    order = [t.label[0] for t in collect([tasks["d"], tasks["e"], graph(log)["c"]]).values()]
    assert sorted(order) == list("abcde")
    assert order.index("a") < order.index("c") < order.index("d") and order.index("b") < order.index("c")


# --- cache ------------------------------------------------------------------------------------------


def test_run_task_publishes_with_manifest_and_skips_when_done(tmp_path, log):
    cache, a = TaskCache(tmp_path / "cache"), graph(log)["a"]
    assert not cache.is_done(a)
    path = cache.run_task(a, {})
    assert path == tmp_path / "cache" / "alpha" / a.key and cache.is_done(a)
    manifest = cache.manifest(a)
    assert manifest["label"] == "a task" and manifest["summary"] == {"total": 1.0} == cache.summary(a)
    assert manifest["params"] == a.params and manifest["code_version"] == a.code_version
    assert cache.path(a.key) == path
    assert cache.run_task(a, {}) == path and calls(log) == ["a"]
    assert tmp_leftovers(cache) == []
    with pytest.raises(TaskError, match=r"task 'c task': no path given for input\(s\) \['x'\]"):
        cache.run_task(graph(log)["c"], {"y": path})


def test_failed_task_leaves_nothing_and_names_itself(tmp_path, log):
    cache, a = TaskCache(tmp_path / "cache"), graph(log)["a"]
    (log / "fail-a").touch()
    with pytest.raises(TaskError, match=r"alpha task 'a task' \(key \w+\) failed: RuntimeError: told to fail a"):
        cache.run_task(a, {})
    assert not cache.path(a).exists() and tmp_leftovers(cache) == [] and cache.entries() == []


def race(out_dir: Path, inputs: dict, *, log: str) -> dict:
    """The first call lets a second worker publish the same key while it is still running."""
    marker = Path(log) / "race"
    if marker.exists():
        marker.unlink()
        TaskCache(Path(log).parent / "cache").run_task(Task("alpha", "race", race, params={"log": log}), {})
        (out_dir / "who").write_text("slow")
        return {"who": "slow"}
    (out_dir / "who").write_text("fast")
    return {"who": "fast"}


def test_second_publisher_of_a_key_discards_its_output(tmp_path, log):
    cache = TaskCache(tmp_path / "cache")
    (log / "race").touch()
    path = cache.run_task(Task("alpha", "race", race, params={"log": str(log)}), {})
    assert (path / "who").read_text() == "fast" and cache.summary(
        Task("alpha", "race", race, params={"log": str(log)})
    ) == {"who": "fast"}
    assert tmp_leftovers(cache) == []


def test_entries_and_clear_by_stage(tmp_path, log):
    cache = TaskCache(tmp_path / "cache")
    tasks = graph(log)
    run(list(tasks.values()), cache, progress=False)
    entries = cache.entries()
    assert sorted((e["stage"], e["label"]) for e in entries) == [
        ("alpha", "a task"),
        ("alpha", "b task"),
        ("alpha", "e task"),
        ("beta", "c task"),
        ("beta", "d task"),
    ]
    assert all(e["bytes"] > len("1.0") and e["created"] for e in entries)
    assert cache.clear("beta") == 2
    assert not cache.is_done(tasks["c"]) and cache.is_done(tasks["a"]) and len(cache.entries()) == 3
    assert cache.clear() == 3 and cache.entries() == [] and tmp_leftovers(cache) == []
    assert TaskCache(tmp_path / "nowhere").entries() == []


def test_clean_stale_tmp_keeps_live_runs(tmp_path, log):
    cache = TaskCache(tmp_path / "cache")
    cache.run_task(graph(log)["a"], {})
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    from admc.pipeline.engine.cache import _host_id

    live = cache.tmp_root / f"{'0' * 20}.{_host_id()}.{os.getpid()}.abcd1234"
    stale = cache.tmp_root / f"{'1' * 20}.{_host_id()}.{dead.pid}.abcd1234"
    for folder in (live, stale):
        folder.mkdir()
        (folder / "partial.bin").write_bytes(b"x" * 10)
    assert cache.clean_stale_tmp() == 1
    assert tmp_leftovers(cache) == [live.name]


# --- runner -----------------------------------------------------------------------------------------


def test_sync_run_executes_each_task_once_then_nothing(tmp_path, log, capfd):
    cache, tasks = TaskCache(tmp_path / "cache"), graph(log)
    published = run([tasks["d"], tasks["e"]], cache, progress=False)
    assert set(published) == {t.key for t in tasks.values()}
    assert totals(published, tasks) == {"a": 1.0, "b": 2.0, "c": 13.0, "d": 114.0, "e": 5.0}
    assert calls(log) == list("abcde")
    assert run([tasks["d"], tasks["e"]], cache, progress=False) == published
    assert calls(log) == list("abcde")
    assert capfd.readouterr() == ("", "")


def test_threads_scheduler_and_progress_output(tmp_path, log, capfd):
    cache, tasks = TaskCache(tmp_path / "cache"), graph(log)
    published = run([tasks["d"], tasks["e"]], cache, scheduler="threads", workers=2, progress=True)
    assert totals(published, tasks)["d"] == 114.0 and calls(log) == list("abcde")
    err = capfd.readouterr().err
    assert "5/5" in err and "task" in err


def test_failure_keeps_published_tasks_and_rerun_runs_only_the_rest(tmp_path, log):
    cache, tasks = TaskCache(tmp_path / "cache"), graph(log)
    (log / "fail-c").touch()
    with pytest.raises(TaskError, match=r"(?s)1 task\(s\) failed, 1 skipped.*3 of 5 are published.*'c task'") as info:
        run([tasks["d"], tasks["e"]], cache, progress=False)
    assert "RuntimeError: told to fail c" in "".join(info.value.__notes__)
    assert {n for n, t in tasks.items() if cache.is_done(t)} == {"a", "b", "e"}
    assert not cache.path(tasks["c"]).exists() and tmp_leftovers(cache) == []
    assert calls(log) == list("abce")
    (log / "fail-c").unlink()
    published = run([tasks["d"], tasks["e"]], cache, progress=False)
    assert calls(log) == sorted("abce" + "cd")
    assert totals(published, tasks)["d"] == 114.0


def test_sigkill_mid_task_leaves_no_published_half_output(tmp_path, log):
    cache, tasks = TaskCache(tmp_path / "cache"), graph(log)
    (log / "slow-c").touch()
    env = {**os.environ, "PYTHONPATH": str(TESTS_DIR)}
    script = f"import test_cache_runner as t; t.run_graph({str(cache.root)!r}, {str(log)!r})"
    proc = subprocess.Popen([sys.executable, "-c", script], env=env)
    try:
        deadline = time.monotonic() + 60
        while not (log / "started-c").exists():
            assert proc.poll() is None, "the run ended before task c started"
            assert time.monotonic() < deadline, "task c never started"
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert not cache.path(tasks["c"]).exists() and not cache.is_done(tasks["d"])
    leftovers = tmp_leftovers(cache)
    assert len(leftovers) == 1 and leftovers[0].startswith(tasks["c"].key)
    assert (cache.tmp_root / leftovers[0] / "partial.txt").exists()  # the half-written output, never published
    done_before = {n for n, t in tasks.items() if cache.is_done(t)}
    assert {"a", "b"} <= done_before and "c" not in done_before
    calls_before = calls(log)
    (log / "slow-c").unlink()
    published = run([tasks["d"], tasks["e"]], cache, progress=False)
    rerun = list(calls(log))
    for name in calls_before:
        rerun.remove(name)
    assert rerun == sorted(set("abcde") - done_before)
    assert totals(published, tasks)["d"] == 114.0 and tmp_leftovers(cache) == []


def test_processes_scheduler_fails_then_resumes_on_a_scheduler_address(tmp_path, log):
    from distributed import LocalCluster

    cache, tasks = TaskCache(tmp_path / "cache"), graph(log)
    (log / "fail-c").touch()
    with pytest.raises(TaskError, match=r"'c task'.*told to fail c"):
        run([tasks["d"], tasks["e"]], cache, scheduler="processes", workers=2, progress=False)
    assert {n for n, t in tasks.items() if cache.is_done(t)} == {"a", "b", "e"}
    assert calls(log) == list("abce") and tmp_leftovers(cache) == []
    (log / "fail-c").unlink()
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        published = run([tasks["d"], tasks["e"]], cache, scheduler=cluster.scheduler_address, progress=False)
    assert calls(log) == sorted("abce" + "cd")
    assert totals(published, tasks) == {"a": 1.0, "b": 2.0, "c": 13.0, "d": 114.0, "e": 5.0}


def test_default_workers():
    assert [default_workers(n) for n in (1, 2, 4, 16, 64)] == [1, 1, 1, 4, 16]
