"""The Dask cluster of a batch localization: a local cluster or a scheduler's address, worker threads, test pauses.

Dask and distributed are the optional extra ``minegeo[dask]``, imported only inside the functions
that start or reach a cluster (:class:`DaskUnavailableError` otherwise). Each worker process runs
its Numba kernels on its share of the cores (:func:`numba_share`) with BLAS on one thread
(:data:`BLAS_THREAD_VARIABLES`).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from minegeo.errors import InputError, OptionalDependencyError

log = logging.getLogger(__name__)


class DaskUnavailableError(OptionalDependencyError):
    """``localize-batch`` needs dask and distributed (``pip install 'minegeo[dask]'``)."""

    def __init__(self):
        super().__init__("dask[distributed]", "dask")


def _client(workers: int, scheduler: str | None, client):
    """``(client, owned)``: the given client, one connected to ``scheduler``, or a local cluster."""
    if client is not None:
        return client, False
    bc = BatchCluster(workers, scheduler)
    bc.start()
    return bc, True


#: test hook: ``MINEGEO_TEST_BATCH_PAUSE=<stage>`` makes the driver wait at that stage (see :func:`pause_for_test`)
TEST_PAUSE_ENV = "MINEGEO_TEST_BATCH_PAUSE"
#: test hook: the file the driver writes when it has reached the stage it waits at
TEST_READY_ENV = "MINEGEO_TEST_BATCH_READY"
#: the stages :func:`pause_for_test` knows, in the order a run reaches them
TEST_STAGES = ("cluster-start", "scans", "commit")


def pause_for_test(stage: str) -> None:
    """Test hook: when ``$MINEGEO_TEST_BATCH_PAUSE`` names ``stage``, write the file
    ``$MINEGEO_TEST_BATCH_READY`` and wait (at most 120 s) for the test's Ctrl-C.

    Stages: ``cluster-start`` (the cluster is starting in its own thread), ``scans`` (the first
    scan has finished, the others are running), ``commit`` (every scan is done; the summary,
    report and record are staged, not yet in place). Without the variable it does nothing.
    """
    if os.environ.get(TEST_PAUSE_ENV) != stage:
        return
    ready = os.environ.get(TEST_READY_ENV)
    if ready:
        Path(ready).write_text(stage, encoding="utf-8")
    deadline = time.monotonic() + 120.0
    while time.monotonic() < deadline:
        time.sleep(0.02)


class BatchCluster:
    """The Dask client of a batch (a local cluster, or a running scheduler's), started so that a
    Ctrl-C leaves nothing running and prints nothing.

    * **Workers never see Ctrl-C, and print nothing.** The terminal's Ctrl-C goes to the whole
      foreground process group, worker processes included. While the local cluster starts, this
      process's stderr and stdout point at ``/dev/null`` (unless ``quiet=False``), so the worker
      processes it spawns inherit them (a worker interrupted while it starts prints nothing), and
      each worker ignores SIGINT once it runs (:mod:`minegeo.localize._batch_worker`, a preload;
      it also silences a worker restarted later). The driver stops the workers itself.
    * **A Ctrl-C while the cluster starts** never interrupts its constructor: the cluster is built
      in a helper thread while the main thread waits; on Ctrl-C the main thread waits for the
      start to end (further Ctrl-C held back), closes what it made, then raises
      :class:`KeyboardInterrupt`. A half-built ``LocalCluster`` would make distributed's exit
      hook fail (``AssertionError: Status.init``).
    * **Quiet.** Unless ``quiet=False``, the ``distributed`` loggers (driver side) print nothing
      while the batch runs and closes; the batch records every scan's outcome itself.

    Parameters
    ----------
    workers : int
        Worker processes of the local cluster, one thread each (ignored with ``scheduler``).
    scheduler : str, optional
        Address of a running ``dask.distributed`` scheduler.
    quiet : bool
        Silence distributed's log lines (default True).
    connect_timeout_s : float
        How long to try reaching ``scheduler`` before giving up (s, default 20).
    """

    def __init__(self, workers: int, scheduler: str | None = None, quiet: bool = True,
                 connect_timeout_s: float = 20.0):
        self.workers = int(workers)
        self.scheduler = scheduler
        self.connect_timeout_s = float(connect_timeout_s)
        self.quiet = quiet
        self.client = None
        self.cluster = None
        self._levels: dict = {}

    # a Client-like face for run_batch
    def submit(self, *a, **k):
        return self.client.submit(*a, **k)

    @property
    def loop(self):
        return self.client.loop

    def _connect(self, box: dict) -> None:
        try:
            from dask.distributed import Client
        except ImportError:
            box["error"] = DaskUnavailableError()
            return
        try:
            if self.scheduler:
                try:
                    box["client"] = Client(self.scheduler, timeout=f"{self.connect_timeout_s}s",
                                           set_as_default=False)
                except (OSError, TimeoutError) as exc:
                    box["error"] = InputError(f"--scheduler {self.scheduler}: cannot connect to the Dask scheduler "
                                              f"within {self.connect_timeout_s:g} s ({exc})")
                return
            from minegeo.localize._batch_worker import QUIET_ENV

            box["cluster"] = local_cluster(self.workers,
                                           silence_logs=(logging.CRITICAL + 1) if self.quiet else logging.ERROR,
                                           preload=["minegeo.localize._batch_worker"],
                                           env={QUIET_ENV: "1" if self.quiet else "0"})
            box["client"] = Client(box["cluster"], set_as_default=False)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread, which raises it
            box["error"] = exc

    def start(self) -> BatchCluster:
        """Start the cluster (or connect); a Ctrl-C meanwhile closes it again and is re-raised."""
        import threading

        from minegeo._output import sigint_deferred

        self._silence()
        box: dict = {}
        t = threading.Thread(target=self._connect, args=(box,), name="minegeo-batch-cluster-start", daemon=True)
        saved = _std_to_devnull() if (self.quiet and not self.scheduler) else None
        try:
            try:
                t.start()
                pause_for_test("cluster-start")
                while t.is_alive():
                    t.join(0.05)
            except BaseException:
                with sigint_deferred():
                    t.join()
                    self.client, self.cluster = box.get("client"), box.get("cluster")
                    self.close()
                raise
        finally:
            _std_restore(saved)
        self.client, self.cluster = box.get("client"), box.get("cluster")
        if "error" in box:
            self.close()
            raise box["error"]
        return self

    def close(self) -> None:
        """Close the client and the local cluster (its worker processes end), with Ctrl-C held back."""
        from minegeo._output import sigint_deferred

        with sigint_deferred():
            try:
                if self.client is not None:
                    try:
                        self.client.close(timeout=30)
                    except Exception as exc:  # noqa: BLE001 - closing a broken connection: nothing left to do
                        log.debug("closing the Dask client: %s", exc)
                if self.cluster is not None:
                    try:
                        self.cluster.close(timeout=30)
                    except Exception as exc:  # noqa: BLE001
                        log.debug("closing the local Dask cluster: %s", exc)
            finally:
                self.client = self.cluster = None
                self._unsilence()

    def _silence(self) -> None:
        if not self.quiet or self._levels:
            return
        for name in ("distributed", "tornado", "asyncio"):
            lg = logging.getLogger(name)
            self._levels[name] = (lg.level, lg.propagate)
            lg.setLevel(logging.CRITICAL + 1)
            lg.propagate = False

    def _unsilence(self) -> None:
        for name, (level, prop) in self._levels.items():
            lg = logging.getLogger(name)
            lg.setLevel(level)
            lg.propagate = prop
        self._levels.clear()

    def __enter__(self) -> BatchCluster:
        return self.start()

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


def _std_to_devnull():
    """Point file descriptors 1 and 2 at ``/dev/null``; returns the saved copies (for :func:`_std_restore`)."""
    import sys

    from minegeo.localize._batch_worker import quiet_std_streams

    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except (AttributeError, ValueError, OSError):
            pass
    saved = (os.dup(1), os.dup(2))
    quiet_std_streams()
    return saved


def _std_restore(saved) -> None:
    if saved is None:
        return
    from minegeo._output import sigint_deferred

    with sigint_deferred():
        for fd, copy in zip((1, 2), saved, strict=True):
            os.dup2(copy, fd)
            os.close(copy)


#: thread-count variables ``distributed`` sets to 1 in every worker it spawns; left as the
#: driver has them (see :func:`local_cluster`)
BLAS_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def local_cluster(workers: int, silence_logs=logging.ERROR, **kwargs):
    """A ``distributed.LocalCluster`` of ``workers`` processes, one thread each, no dashboard,
    whose workers keep the driver's BLAS thread settings; ``kwargs`` go to ``LocalCluster`` (and
    on to each worker's nanny: ``preload``, ``env``).

    ``distributed`` starts workers with ``OMP/MKL/OPENBLAS_NUM_THREADS=1``
    (``distributed.nanny.pre-spawn-environ``); minegeo's covariance goes through BLAS, whose
    sums depend on its thread count in the last bits (measured: a jackknife covariance differed
    at 1e-16 relative between 1 and 2 OpenBLAS threads). Workers with the driver's settings give
    the bits ``minegeo localize`` gives in the same shell. Numba's threads are shared out instead
    (cores // workers per worker unless ``NUMBA_NUM_THREADS`` is set): minegeo's parallel kernels
    give the same bits for any thread count (the kernel tests check it; the batch tests compare
    workers of 1 and 2 Numba threads with a 2-thread ``localize``).

    The Numba share is applied inside each task (:attr:`BatchJob.numba_threads`,
    ``numba.set_num_threads``), not through the spawn environment: ``distributed`` writes the
    spawn environment into the *driver's* ``os.environ`` (at every worker start and restart) and
    never takes it back, and a ``NUMBA_NUM_THREADS`` there that differs from the driver's running
    thread pool makes Numba refuse every later compilation in the driver.
    """
    try:
        import dask
        from dask.distributed import LocalCluster
    except ImportError:
        raise DaskUnavailableError() from None
    env = {k: v for k, v in (dask.config.get("distributed.nanny.pre-spawn-environ", {}) or {}).items()
           if k not in BLAS_THREAD_VARIABLES and not k.startswith("NUMBA_")}
    before = {k: os.environ.get(k) for k in env}
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": env}):
            return LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                dashboard_address=None, silence_logs=silence_logs, **kwargs)
    finally:  # the nannies wrote env into this process's os.environ: put it back
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def numba_share(workers: int, scheduler: str | None) -> int:
    """Numba threads per worker of a local cluster: ``cores // workers`` (0 = leave the worker's
    default: with ``--scheduler``, or when ``NUMBA_NUM_THREADS`` is set by the user)."""
    if scheduler or "NUMBA_NUM_THREADS" in os.environ:
        return 0
    return max(1, (os.cpu_count() or 1) // max(1, int(workers)))


def apply_numba_share(n: int) -> None:
    """In a worker: use at most ``n`` Numba threads (0: unchanged)."""
    if n > 0:
        import numba

        numba.set_num_threads(max(1, min(int(n), int(numba.config.NUMBA_NUM_THREADS))))
