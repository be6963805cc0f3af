"""Dask worker preload of ``minegeo localize-batch``'s local cluster (``preload=[__name__]``).

A Ctrl-C in the terminal goes to the whole foreground process group, worker processes
included. Stopping the batch is the driver's business (it closes the cluster and takes back what
the run wrote), so each worker process ignores SIGINT from the moment it starts its worker,
and, when the driver asks for quiet workers (``MINEGEO_BATCH_QUIET_WORKERS=1`` in the worker's
environment: every run but ``--debug``), sends its own stdout and stderr to ``/dev/null``: the
batch records every scan's outcome in its result folder, and a worker's log lines or a
traceback as it is stopped would only bury the run's one-line message.
"""

from __future__ import annotations

import os
import signal
import threading

#: the worker environment variable that asks for quiet workers
QUIET_ENV = "MINEGEO_BATCH_QUIET_WORKERS"


def dask_setup(worker) -> None:  # noqa: ARG001 - distributed's preload hook signature
    """Run by distributed in each worker process as its worker starts."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    if os.environ.get(QUIET_ENV) == "1":
        quiet_std_streams()


def quiet_std_streams() -> None:
    """Point file descriptors 1 and 2 of this process at ``/dev/null`` (a worker as it starts; the driver
    around its cluster's start, :func:`minegeo.localize.batch_cluster._std_to_devnull`, which keeps copies to restore)."""
    fd = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(fd, 1)
        os.dup2(fd, 2)
    finally:
        os.close(fd)
