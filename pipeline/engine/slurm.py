"""`run.scheduler = "slurm"`: a dask-jobqueue SLURMCluster sized by the config's [cluster] section.

Each SLURM job runs one dask worker with one thread (one task at a time, like the local cluster:
a render already uses every core it is given) on `cluster.cores` CPUs, `cluster.memory` and
`cluster.gpus` GPUs. The scheduler runs inside the `admc-pipe` process, so it lives as long as the
command; the workers must see the same `run.workdir` (a shared filesystem).
"""
from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path

from admc.errors import AdmcError
from admc.pipeline.config import Config

SLURM = "slurm"


class ClusterError(AdmcError, ValueError):
    """The SLURM cluster cannot be set up as configured (e.g. the optional extra is missing)."""


def job_options(cfg: Config) -> dict:
    """SLURMCluster keyword arguments for the [cluster] section (one single-threaded worker per job)."""
    c = cfg.cluster
    gres = [f"--gres=gpu:{c.gpus}"] if c.gpus else []
    return {
        "cores": 1, "processes": 1,  # worker threads: one task at a time per job
        "job_cpu": c.cores, "memory": c.memory, "walltime": c.walltime,
        "queue": c.queue or None, "account": c.account or None, "interface": c.interface or None,
        "job_extra_directives": [*gres, *c.job_directives],
        "job_name": "admc", "python": sys.executable,
        "log_directory": str(Path(cfg.run.workdir).resolve() / "slurm-logs"),
    }


def slurm_cluster(cfg: Config):
    """A SLURMCluster (its scheduler starts here, no jobs yet); ClusterError when dask-jobqueue is absent."""
    try:
        from dask_jobqueue import SLURMCluster
    except ImportError:
        raise ClusterError("config key 'run.scheduler' is 'slurm', which needs the optional dask-jobqueue "
                           "package: pip install 'admc[cluster]' (or '.[cluster]' in a checkout)") from None
    return SLURMCluster(**job_options(cfg))


@contextlib.contextmanager
def scheduler_address(cfg: Config) -> Iterator[str]:
    """run.scheduler as the runner takes it; for "slurm", the address of a cluster of cluster.jobs jobs."""
    if cfg.run.scheduler != SLURM:
        yield cfg.run.scheduler
        return
    with slurm_cluster(cfg) as cluster:
        cluster.scale(jobs=cfg.cluster.jobs)
        yield cluster.scheduler_address
