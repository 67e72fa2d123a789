"""run.scheduler = "slurm": the job script dask-jobqueue generates from [cluster] (no SLURM needed) and
the errors a user sees for a missing extra or a bad [cluster] value."""

from __future__ import annotations

import sys

import pytest

from admc.errors import AdmcError
from admc.pipeline.config import ConfigError, load_config
from admc.pipeline.engine import slurm


def _cfg(tmp_path, *overrides: str):
    return load_config(None, [f"run.workdir='{tmp_path}'", "run.scheduler=slurm", *overrides])


def _sbatch_lines(cfg) -> tuple[list[str], str]:
    pytest.importorskip("dask_jobqueue", reason="the optional extra is not installed: pip install '.[cluster]'")
    with slurm.slurm_cluster(cfg.cluster, cfg.workdir_path("slurm-logs").resolve()) as cluster:
        script = cluster.job_script()
    lines = script.splitlines()
    return [line.removeprefix("#SBATCH ") for line in lines if line.startswith("#SBATCH")], lines[-1]


def test_job_script_books_the_configured_resources(tmp_path):
    cfg = _cfg(
        tmp_path,
        "cluster.cores=12",
        "cluster.memory='48GiB'",
        "cluster.gpus=2",
        "cluster.queue=gpu",
        "cluster.account=render-proj",
        "cluster.walltime='1-02:30:00'",
        "cluster.job_directives=['--constraint=a100', '--qos=long']",
    )
    directives, worker = _sbatch_lines(cfg)
    logs = tmp_path / "slurm-logs"
    assert directives == [
        "-J admc",
        f"-e {logs}/admc-%J.err",
        f"-o {logs}/admc-%J.out",
        "-p gpu",
        "-A render-proj",
        "-n 1",
        "--cpus-per-task=12",
        "--mem=48G",
        "-t 1-02:30:00",
        "--gres=gpu:2",
        "--constraint=a100",
        "--qos=long",
    ]
    assert worker.startswith(f"{sys.executable} -m distributed.cli.dask_worker tcp://")
    assert " --nthreads 1 " in worker and "--memory-limit 48.00GiB" in worker  # one task at a time per job


def test_defaults_book_no_gpu_and_leave_partition_and_account_to_the_site(tmp_path):
    directives, _ = _sbatch_lines(_cfg(tmp_path))
    assert not [d for d in directives if d.startswith(("-p ", "-A ", "--gres"))]
    assert "--cpus-per-task=8" in directives and "--mem=32G" in directives and "-t 04:00:00" in directives


def test_missing_extra_is_a_user_error_naming_the_key(tmp_path, monkeypatch, variant):
    from admc.pipeline.stages.render import render_corpus

    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)  # what `import dask_jobqueue` sees when it is absent
    cfg = _cfg(tmp_path, "corpus.n_scenes=1", "render.resolution=[8, 8]")
    with pytest.raises(slurm.ClusterError, match=r"'run.scheduler' is 'slurm'.*pip install 'admc\[cluster\]'"):
        render_corpus(cfg, progress=False)
    assert issubclass(slurm.ClusterError, AdmcError)
    assert not (tmp_path / "cache" / "render").exists()  # stopped before any task ran


def test_other_schedulers_pass_through(tmp_path):
    cfg = load_config(None, ["run.scheduler=tcp://10.0.0.5:8786"])
    with slurm.scheduler_address(cfg.run.scheduler, cfg.cluster, tmp_path) as address:
        assert address == "tcp://10.0.0.5:8786"


@pytest.mark.parametrize(
    "override, key",
    [
        ("cluster.jobs=0", "cluster.jobs"),
        ("cluster.cores=0", "cluster.cores"),
        ("cluster.gpus=-1", "cluster.gpus"),
        ("cluster.memory='lots'", "cluster.memory"),
        ("cluster.walltime='4h'", "cluster.walltime"),
        ("cluster.job_directives=['constraint=a100']", r"cluster.job_directives\[0\]"),
        ("cluster.partition='gpu'", "cluster.partition"),
    ],
)
def test_bad_cluster_value_names_its_key(tmp_path, override, key):
    with pytest.raises(ConfigError, match=f"'{key}'"):
        _cfg(tmp_path, override)
