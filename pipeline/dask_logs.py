"""dask's log lines of a run to a file, not to the command's terminal (``pipeline.execute.Scheduler``).

Imported only when a run uses a dask.distributed cluster (it imports distributed).
"""
from __future__ import annotations

import logging
from pathlib import Path

from distributed.diagnostics.plugin import WorkerPlugin

DASK_LOGGERS = ("distributed", "bokeh", "tornado")
LOG_FORMAT = "%(asctime)s %(process)d %(name)s %(levelname)s: %(message)s"


def _to_file(handler: logging.Handler) -> None:
    for name in DASK_LOGGERS:
        lg = logging.getLogger(name)
        lg.handlers = [handler]
        lg.setLevel(logging.INFO)
        lg.propagate = False


# A worker process configures its logging when it imports distributed, from the environment it inherits: until its
# plugin (WorkerLogsToFile) runs, it prints only errors (none are expected before its first task).
WORKER_START_ENV = {"DASK_LOGGING__DISTRIBUTED": "error"}


class DaskLogs:
    """While a cluster is in use, this process's dask loggers (scheduler, nannies, client, the dashboard's web
    server) write to ``path`` at INFO and nowhere else, and the worker processes it starts inherit
    ``WORKER_START_ENV``; ``restore`` puts both back."""

    def __init__(self, path: Path):
        import os

        self._handler = logging.FileHandler(path, encoding="utf-8")
        self._handler.setFormatter(logging.Formatter(LOG_FORMAT))
        self._saved = {}
        for name in DASK_LOGGERS:
            lg = logging.getLogger(name)
            self._saved[name] = (list(lg.handlers), lg.level, lg.propagate)
        _to_file(self._handler)
        self._env = {k: os.environ.get(k) for k in WORKER_START_ENV}
        os.environ.update(WORKER_START_ENV)

    def restore(self) -> None:
        import os

        for name, (handlers, level, propagate) in self._saved.items():
            lg = logging.getLogger(name)
            lg.handlers, lg.propagate = handlers, propagate
            lg.setLevel(level)
        self._handler.close()
        for k, v in self._env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class WorkerLogsToFile(WorkerPlugin):
    """On every worker of the run's cluster (started now or later): its dask log lines to the run's log file (at
    INFO), not to its stderr (the command's terminal). A task's exception still reaches the client."""

    def __init__(self, path: str):
        self.path = path

    def setup(self, worker) -> None:
        handler = logging.FileHandler(self.path, encoding="utf-8")
        handler.setFormatter(logging.Formatter(LOG_FORMAT))
        _to_file(handler)
