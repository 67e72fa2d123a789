"""`run.scheduler = "slurm"`: a dask-jobqueue SLURMCluster sized by the config's [cluster] section.

Each SLURM job runs one dask worker with one thread (one task at a time, like the local cluster:
a render already uses every core it is given) on `cluster.cores` CPUs, `cluster.memory` and
`cluster.gpus` GPUs. The scheduler runs inside the `admc-pipe` process, so it lives as long as the
command; the workers must see the same `run.workdir` (a shared filesystem), where `log_dir` lies.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path

from admc.errors import AdmcError
from admc.pipeline.config import ClusterConfig

SLURM = "slurm"


class ClusterError(AdmcError, ValueError):
    """The SLURM cluster cannot be set up as configured (e.g. the optional extra is missing)."""


def job_options(cluster: ClusterConfig, log_dir: Path) -> dict:
    """SLURMCluster keyword arguments for the [cluster] section (one single-threaded worker per job), the
    jobs' logs under `log_dir`."""
    gres = [f"--gres=gpu:{cluster.gpus}"] if cluster.gpus else []
    return {
        "cores": 1,
        "processes": 1,  # worker threads: one task at a time per job
        "job_cpu": cluster.cores,
        "memory": cluster.memory,
        "walltime": cluster.walltime,
        "queue": cluster.queue or None,
        "account": cluster.account or None,
        "interface": cluster.interface or None,
        "job_extra_directives": [*gres, *cluster.job_directives],
        "job_name": "admc",
        "python": sys.executable,
        "log_directory": str(log_dir),
    }


def slurm_cluster(cluster: ClusterConfig, log_dir: Path):
    """A SLURMCluster (its scheduler starts here, no jobs yet); ClusterError when dask-jobqueue is absent."""
    try:
        from dask_jobqueue import SLURMCluster
    except ImportError:
        raise ClusterError(
            "config key 'run.scheduler' is 'slurm', which needs the optional dask-jobqueue "
            "package: pip install 'admc[cluster]' (or '.[cluster]' in a checkout)"
        ) from None
    return SLURMCluster(**job_options(cluster, log_dir))


@contextlib.contextmanager
def scheduler_address(scheduler: str, cluster: ClusterConfig, log_dir: Path) -> Iterator[str]:
    """run.scheduler as the runner takes it; for "slurm", the address of a cluster of cluster.jobs jobs
    (`cluster`), their logs under `log_dir`."""
    if scheduler != SLURM:
        yield scheduler
        return
    with slurm_cluster(cluster, log_dir) as jobs:
        jobs.scale(jobs=cluster.jobs)
        yield jobs.scheduler_address
