"""Running study / tune jobs on a Dask cluster (``distributed``): ``--workers N`` starts an
embedded local cluster of N worker processes bound to 127.0.0.1, ``--scheduler ADDRESS`` uses a
cluster that is already running.

Every run is one task (:func:`warpfem.tradeoff.runner.run_job`): it builds the variant, warms the
worker's kernels for its signature (one untimed frame), then runs and times it on that worker, so
wall times are the worker's own. A task whose worker dies (or that raises) is submitted again, up
to ``retries`` times; the retry is written into that run's note, and a run that still fails comes
back as a failed row, never silently dropped. The embedded cluster is started with
``distributed.scheduler.allowed-failures = 0`` so that a worker death reaches this client at
once (and is counted here); on an external cluster the scheduler may first reschedule the task
itself: those restarts are found in the workers' event log (every run logs its start) and reported
the same way.

Needs the optional extra: ``pip install 'warpfem[dask]'``. Workers of an external cluster must
see the scene's files (mesh, surface) at the same paths as this machine and have warpfem installed.
"""

from __future__ import annotations

import os

import logging
import uuid

__all__ = ["DaskExecutor", "JobFailed", "require_distributed"]

log = logging.getLogger(__name__)

EVENT_TOPIC = "warpfem-job-start"


def require_distributed():
    """Import ``distributed`` or raise ImportError naming the extra to install."""
    try:
        import dask  # noqa: F401
        import distributed
    except ImportError as e:
        raise ImportError("running on a Dask cluster (--workers / --scheduler) needs dask.distributed, which is not "
                          "installed: pip install 'warpfem[dask]' (or pip install distributed)") from e
    return distributed


class JobFailed:
    """A job that did not come back after its retries (the executor's result in its place)."""

    def __init__(self, attempts: int, errors: list):
        self.attempts, self.errors = attempts, list(errors)

    @property
    def message(self) -> str:
        return f"failed on the cluster after {self.attempts} attempt(s): " + "; ".join(self.errors)


class DaskExecutor:
    """Map jobs onto Dask workers (see the module docstring).

    ``workers``: start an embedded local cluster of that many single-threaded worker processes on
    127.0.0.1 (no other address). ``scheduler``: the address of a running scheduler instead.
    ``retries``: resubmissions of a job whose worker died or that raised. Use as a context manager
    (or call :meth:`close`) to stop the embedded cluster.
    """

    def __init__(self, *, workers: int | None = None, scheduler: str | None = None, retries: int = 2,
                 memory_limit="auto"):
        require_distributed()
        import dask
        from distributed import Client, LocalCluster

        if (workers is None) == (scheduler is None):
            raise ValueError("give exactly one of workers (embedded local cluster) or scheduler (an address)")
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
            raise ValueError(f"retries must be an integer >= 0, got {retries!r}")
        self.retries = retries
        self.cluster = None
        self.retried: dict = {}  # job index -> ["attempt 1: KilledWorker: ...", ...]
        if workers is not None:
            # Dask's nanny sets OMP/MKL/OPENBLAS_NUM_THREADS = 1 in its workers; the sparse direct solver
            # (MKL PARDISO) sums in another order with another thread count, so a worker would differ from
            # the serial run in the last bits. Workers get this process's own settings instead.
            environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
                       if not k.endswith("_NUM_THREADS")}
            environ.update({k: os.environ[k] for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
                            if k in os.environ})
            with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                                  "distributed.nanny.pre-spawn-environ": environ}):
                self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                                            dashboard_address=None, memory_limit=memory_limit)
            self.client = Client(self.cluster)
            self.description = f"dask: embedded local cluster, {workers} worker process(es) on 127.0.0.1"
        else:
            self.client = Client(scheduler)
            self.description = f"dask: scheduler {scheduler}"

    # context manager
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()
                self.cluster = None

    def worker_addresses(self) -> list:
        return sorted(self.client.scheduler_info().get("workers", {}))

    def map(self, fn, jobs, *, on_done=None, progress=None):
        """Run ``fn(job)`` for every job on the cluster; results in job order (a :class:`JobFailed`
        where a job failed ``retries + 1`` times). ``on_done(i, result)`` as each one completes;
        ``progress`` (per-frame callbacks) is not available on a cluster and is ignored."""
        from distributed import as_completed

        tag = uuid.uuid4().hex[:8]
        jobs = [dict(job, job_id=f"{tag}-{i}") if isinstance(job, dict) else job for i, job in enumerate(jobs)]
        n = len(jobs)
        results = [None] * n
        attempts = [0] * n
        errors = [[] for _ in range(n)]
        self.retried = {}

        def submit(i):
            attempts[i] += 1
            return self.client.submit(fn, jobs[i], pure=False, key=f"warpfem-{tag}-{i}-{attempts[i]}")

        owner = {}
        for i in range(n):
            owner[submit(i)] = i
        pending = as_completed(list(owner))
        for fut in pending:
            i = owner.pop(fut)
            try:
                r = fut.result()
            except Exception as e:  # noqa: BLE001 - a dead worker (KilledWorker) or the job's own error
                if type(e).__name__ == "KilledWorker":
                    last = str(e).split("The last worker that attempt to run the task was ")[-1].split(". ")[0]
                    msg = f"attempt {attempts[i]}: its worker died (KilledWorker; {last})"
                else:
                    msg = f"attempt {attempts[i]}: {type(e).__name__}: {str(e)[:300]}"
                errors[i].append(msg)
                log.warning("job %d: %s", i, msg)
                fut.release()
                if attempts[i] <= self.retries:
                    nf = submit(i)
                    owner[nf] = i
                    pending.add(nf)
                    continue
                r = JobFailed(attempts[i], errors[i])
            fut.release()
            if errors[i]:
                self.retried[i] = list(errors[i])
            results[i] = r
            if on_done is not None:
                on_done(i, r)
        # restarts the scheduler did by itself (external clusters): more logged starts than submissions
        try:
            starts = {}
            for _, ev in self.client.get_events(EVENT_TOPIC):
                if isinstance(ev, dict) and str(ev.get("job_id", "")).startswith(tag):
                    starts[ev["job_id"]] = starts.get(ev["job_id"], 0) + 1
            for i in range(n):
                extra = starts.get(f"{tag}-{i}", 0) - attempts[i]
                if extra > 0:
                    self.retried.setdefault(i, []).append(f"restarted {extra} time(s) by the scheduler (a worker was lost)")
        except Exception:  # noqa: BLE001 - reporting only
            pass
        return results


def log_job_start(job) -> None:
    """Called by a job on a Dask worker: records its start in the workers' event log."""
    try:
        from distributed import get_worker

        w = get_worker()
    except (ImportError, ValueError):
        return
    try:
        w.log_event(EVENT_TOPIC, {"job_id": job.get("job_id"), "worker": w.address})
    except Exception:  # noqa: BLE001 - reporting only
        pass


def _die_once(job: dict):
    """Test helper: the first call (no marker file yet) kills its worker process; later calls
    return ``2 * job["value"]``. ``job["always"]``: die every time."""
    import os

    log_job_start(job)
    if job.get("always") or not os.path.exists(job["marker"]):
        open(job["marker"], "w").close()
        os._exit(13)
    return 2 * job["value"]


# ----------------------------------------------------------------------------- command-line helpers
def add_cluster_args(p) -> None:
    """``--workers N`` / ``--scheduler ADDRESS`` / ``--retries K`` (tradeoff and tune)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="run on an embedded Dask cluster of N worker processes on this machine (127.0.0.1 only); "
                        "needs warpfem[dask]")
    g.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run on the Dask cluster whose scheduler is at ADDRESS (e.g. tcp://10.0.0.5:8786)")
    p.add_argument("--retries", type=int, default=2, metavar="K",
                   help="resubmissions of a run whose worker died or that raised (cluster runs; default 2)")


def executor_from_args(args, err):
    """(executor or None, exit code or None): None/None = run serially; checks before anything runs."""
    workers, scheduler = getattr(args, "workers", None), getattr(args, "scheduler", None)
    if workers is None and scheduler is None:
        return None, None
    if workers is not None and workers < 1:
        err(f"--workers must be >= 1, got {workers}")
        return None, 2
    if args.retries < 0:
        err(f"--retries must be >= 0, got {args.retries}")
        return None, 2
    try:
        require_distributed()
    except ImportError as e:
        err(str(e))
        return None, 2
    try:
        return DaskExecutor(workers=workers, scheduler=scheduler, retries=args.retries), None
    except (OSError, TimeoutError, RuntimeError, ValueError) as e:
        err(f"could not start / reach the Dask cluster: {type(e).__name__}: {e}")
        return None, 1
