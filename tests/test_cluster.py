"""A real dask cluster on loopback: `dask scheduler` and two `dask worker` processes started with the CLIs,
as an operator would, and `admc-pipe dataset --scheduler tcp://...` as a separate client process.

The result must equal a local `run.scheduler=sync` run of the same config (EXR pixels and patch rows),
and a worker SIGKILLed mid-render must cost only its running task.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from admc.pipeline.engine.cache import MANIFEST, TMP_DIR
from admc.stores.exr import read_exr

pytestmark = pytest.mark.slow

BIN = Path(sys.executable).parent
TINY = [
    "render.resolution=[32, 32]",
    "render.spp=[2, 4]",
    "render.reference_spp=16",
    "corpus.n_scenes=4",
    "corpus.families=['room', 'tabletop']",
    "tile.patch_size=32",
    "tile.crops_per_scene=3",
    "tile.split=[0.5, 0.5, 0.0]",
]
N_TASKS = 4 * 3 + 4  # 4 scenes x (2 noisy + 1 reference) renders, one tile task per scene
WAIT_S = 120  # the bound on every wait: generous for a contended 2-core CI machine


def _wait_for(condition, what: str, timeout: float = WAIT_S, every: float = 0.02):
    """Poll until condition() returns something truthy; fail naming what never happened."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(every)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")


class LoopbackCluster:
    """A dask scheduler and workers as separate OS processes; stop() kills every one of them."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.procs: list[subprocess.Popen] = []
        self.workers: list[subprocess.Popen] = []
        self.address = ""

    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen:
        log = open(self.folder / f"{name}.log", "wb")
        proc = subprocess.Popen(
            [str(BIN / "dask"), *args], stdout=log, stderr=subprocess.STDOUT, cwd=self.folder, start_new_session=True
        )
        log.close()
        self.procs.append(proc)
        return proc

    def start(self, n_workers: int) -> LoopbackCluster:
        info = self.folder / "scheduler.json"
        scheduler = self._spawn(
            "scheduler",
            ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", str(info)],
        )
        self.address = _wait_for(
            lambda: (
                info.is_file()
                and json.loads(info.read_text() or "{}").get("address")
                or scheduler.poll() is not None
                and pytest.fail(self.logs())
            ),
            "the scheduler's address file",
        )
        for i in range(n_workers):
            # --no-nanny: the worker process is the one that renders, so a SIGKILL ends it for good
            # (under a nanny the nanny would start a fresh worker, and the lost task might rerun there).
            self.workers.append(
                self._spawn(
                    f"worker{i}",
                    [
                        "worker",
                        self.address,
                        "--nthreads",
                        "1",
                        "--nworkers",
                        "1",
                        "--no-nanny",
                        "--no-dashboard",
                        "--name",
                        f"w{i}",
                        "--local-directory",
                        str(self.folder / f"w{i}"),
                        "--death-timeout",
                        "60",
                    ],
                )
            )
        from distributed import Client

        with Client(self.address, timeout=WAIT_S) as client:
            client.wait_for_workers(n_workers, timeout=WAIT_S)
        return self

    def logs(self) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}" for p in sorted(self.folder.glob("*.log")))

    def stop(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)  # its own session: the process and any child it started
            proc.wait(timeout=WAIT_S)


@pytest.fixture
def cluster(tmp_path):
    folder = tmp_path / "cluster"
    folder.mkdir()
    running = LoopbackCluster(folder)
    try:
        yield running.start(n_workers=2)
    finally:
        running.stop()


def _admc(workdir: Path, *args: str) -> list[str]:
    sets = [item for s in [f"run.workdir='{workdir}'", *TINY] for item in ("--set", s)]
    return [str(BIN / "admc-pipe"), "dataset", *sets, *args]


def _dataset(workdir: Path, *args: str, cwd: Path | None = None) -> str:
    done = subprocess.run(_admc(workdir, *args), capture_output=True, text=True, timeout=600, cwd=cwd)
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout + done.stderr


@pytest.fixture(scope="module")
def local_run(tmp_path_factory) -> Path:
    """The same corpus with the in-process scheduler: what every cluster run must reproduce."""
    workdir = tmp_path_factory.mktemp("local")
    _dataset(workdir, "--scheduler", "sync")
    return workdir


def _renders(workdir: Path) -> dict[str, dict[str, np.ndarray]]:
    return {f"{p.parent.name}/{p.name}": read_exr(p) for p in sorted((workdir / "renders").glob("*/*.exr"))}


def _store_arrays(workdir: Path) -> dict[str, np.ndarray]:
    root = zarr.open_group(workdir / "patches.zarr", mode="r")
    return {name: node[...] for name, node in root.members(max_depth=None) if isinstance(node, zarr.Array)}


def _assert_same_dataset(workdir: Path, reference: Path) -> None:
    mine, theirs = _renders(workdir), _renders(reference)
    assert sorted(mine) == sorted(theirs) and len(mine) == 12
    for name, layers in theirs.items():
        assert sorted(mine[name]) == sorted(layers), name
        for layer, pixels in layers.items():
            np.testing.assert_array_equal(mine[name][layer], pixels, err_msg=f"{name} {layer}")
    rows, expected = _store_arrays(workdir), _store_arrays(reference)
    assert sorted(rows) == sorted(expected) and rows
    for name, values in expected.items():
        np.testing.assert_array_equal(rows[name], values, err_msg=name)


def _progress_lines(output: str) -> list[str]:
    return re.findall(r"^\[(\d+)/(\d+)\] done (.+)$", output, flags=re.MULTILINE)


def _published(workdir: Path) -> list[Path]:
    cache = workdir / "cache"
    return [entry for stage in cache.iterdir() if stage.name != TMP_DIR for entry in stage.iterdir()]


def test_cli_cluster_run_equals_a_local_run(cluster, local_run, tmp_path):
    # a relative run.workdir: the workers run in another folder and must still write where the client reads
    output = _dataset(Path("on-cluster"), "--scheduler", cluster.address, cwd=tmp_path)
    workdir = tmp_path / "on-cluster"
    assert f"{N_TASKS} tasks run, 0 cached" in output
    _assert_same_dataset(workdir, local_run)
    lines = _progress_lines(output)  # off a terminal: one plain line per finished task
    assert [int(done) for done, _total, _label in lines] == list(range(1, N_TASKS + 1))
    assert len({label for *_, label in lines}) == N_TASKS


def test_a_worker_killed_mid_render_costs_only_its_task(cluster, local_run, tmp_path):
    workdir = tmp_path / "on-cluster"
    tmp_root = workdir / "cache" / TMP_DIR
    log = open(tmp_path / "client.log", "w+")
    client = subprocess.Popen(
        _admc(workdir, "--scheduler", cluster.address),
        stdout=log,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        victim = cluster.workers[0]

        def victims_task() -> list[Path]:
            # a task's temp folder is named <key>.<host>.<pid>.<uuid>: the victim is working on it now
            return tmp_root.is_dir() and [p for p in tmp_root.iterdir() if p.name.split(".")[2:3] == [str(victim.pid)]]

        running = _wait_for(victims_task, "worker w0 to start a task")
        os.kill(victim.pid, signal.SIGKILL)
        victim.wait(timeout=WAIT_S)
        lost_key = running[0].name.split(".")[0]
        assert client.wait(timeout=600) == 0, cluster.logs() + Path(log.name).read_text()
    finally:
        if client.poll() is None:
            os.killpg(client.pid, signal.SIGKILL)
            client.wait(timeout=WAIT_S)
        log.close()
    output = Path(log.name).read_text()
    assert f"{N_TASKS} tasks run, 0 cached" in output
    assert cluster.workers[1].poll() is None  # the survivor did the rest

    published = _published(workdir)
    assert len(published) == N_TASKS and all((p / MANIFEST).is_file() for p in published)
    assert lost_key in {p.name for p in published if p.parent.name == "render"}  # the lost render ran again
    leftovers = [p.name for p in tmp_root.iterdir()]
    assert leftovers == [running[0].name]  # only the killed attempt's temp folder, never counted as done
    _assert_same_dataset(workdir, local_run)
    assert len(_progress_lines(output)) == N_TASKS

    rerun = _dataset(workdir, "--scheduler", cluster.address)
    assert f"0 tasks run, {N_TASKS} cached" in rerun
    assert list(tmp_root.iterdir()) == []  # the dead worker's temp folder is cleaned as stale
