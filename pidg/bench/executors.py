"""Where a benchmark's jobs run: one after the other here, in a local process pool, or as Ray tasks on a cluster.

An executor gets the jobs, the function that runs one (``work(job) -> rows``; it must not raise, see
:func:`pidg.bench.suite.run_job`), ``crashed(job, message) -> rows`` for a job whose worker died (a segfault, an
out-of-memory kill, a lost node), and ``on_rows`` to hand each job's rows over as they arrive. It never lets one
job's failure stop the others. Executors know nothing about what a job is: the suite passes its functions in.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import re
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, Callable, Literal, Sequence

import torch

logger = logging.getLogger(__name__)

ExecutorName = Literal["local", "process", "ray"]
Work = Callable[[Any], list[dict]]
Crashed = Callable[[Any, str], list[dict]]
OnRows = Callable[[list[dict]], None]

RAY_HINT = "the ray executor needs Ray: pip install 'ray>=2.9' (or pip install -e '.[ray]')"


def make_executor(
    name: ExecutorName, workers: int = 2, address: str | None = None, gpus_per_job: float | None = None,
    cpus_per_job: float = 1.0,
) -> Callable[[Sequence[Any], Work, Crashed, OnRows], None]:
    """The executor called ``name`` with its settings bound."""
    if name == "local":
        return run_local
    if name == "process":
        return lambda jobs, work, crashed, on_rows: run_process_pool(jobs, work, crashed, on_rows, workers)
    if name == "ray":
        return lambda jobs, work, crashed, on_rows: run_ray(jobs, work, crashed, on_rows, address, gpus_per_job, cpus_per_job)
    raise ValueError(f"executor must be local, process or ray, got {name!r}")


def run_local(jobs: Sequence[Any], work: Work, crashed: Crashed, on_rows: OnRows) -> None:
    """One job after the other in this process (the default: nothing else competes for the CPU or GPU)."""
    for job in jobs:
        on_rows(work(job))


def _limit_threads(threads: int) -> None:
    torch.set_num_threads(threads)


def run_process_pool(jobs: Sequence[Any], work: Work, crashed: Crashed, on_rows: OnRows, workers: int = 2) -> None:
    """``workers`` jobs at a time in fresh processes (spawned: no inherited torch or numba state), the CPU cores
    shared evenly between them. On CPU, timings of jobs that ran side by side are not comparable with single runs."""
    threads = max(1, (os.cpu_count() or 1) // workers)
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_limit_threads, initargs=(threads,)) as pool:
        futures = {pool.submit(work, job): job for job in jobs}
        for future in as_completed(futures):
            try:
                rows = future.result()
            except Exception as err:  # noqa: BLE001 - a dead worker fails its job only
                rows = crashed(futures[future], f"worker process died: {type(err).__name__}: {err}")
            on_rows(rows)


def run_ray(
    jobs: Sequence[Any], work: Work, crashed: Crashed, on_rows: OnRows, address: str | None = None,
    gpus_per_job: float | None = None, cpus_per_job: float = 1.0,
) -> None:
    """Each job as a Ray task: on the cluster at ``address`` (``auto``: the one this machine belongs to), or on a
    local Ray instance started here when None. With GPUs in the cluster each task gets one (``gpus_per_job``
    overrides). A task that raises or whose worker dies becomes a failed row; the other tasks go on."""
    try:
        import ray  # optional extra; imported only when this executor is chosen
    except ImportError as err:
        raise ImportError(RAY_HINT) from err
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    try:
        if gpus_per_job is None:
            gpus_per_job = 1.0 if ray.cluster_resources().get("GPU", 0) > 0 else 0.0
        remote = ray.remote(num_cpus=cpus_per_job, num_gpus=gpus_per_job, max_retries=0)(work)
        pending = {remote.remote(job): job for job in jobs}
        logger.info("ray: %d tasks, %s CPU and %s GPU each", len(pending), cpus_per_job, gpus_per_job)
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            ref = done[0]
            job = pending.pop(ref)
            try:
                rows = ray.get(ref)
            except Exception as err:  # noqa: BLE001 - RayTaskError, WorkerCrashedError, ...: this job only
                text = " ".join(re.sub(r"\x1b\[[0-9;]*m", "", str(err)).split())  # no terminal colours in tables
                rows = crashed(job, f"ray task failed: {type(err).__name__}: {text[:300]}")
            on_rows(rows)
    finally:
        if started_here:
            ray.shutdown()
