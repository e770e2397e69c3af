"""The service's other HTTP processes (``settings.http_processes`` > 1; docs/service.md).

An upload's work in the API process is Python (HTTP, multipart, decoding, staging), so one
process answers at most about one core's worth of requests, whatever the machine has. With
``http_processes`` = N, ``rangefuse serve`` (the *primary*) binds the socket, takes back the
uploads a crash left half-done, starts the job runner, and then starts N - 1 more processes
that answer requests on the same socket (inherited: the kernel hands each new connection to
one of the processes waiting on it). They share everything through the store and its
catalog, as the primary's own request threads do: uploads are archived and committed by the
process that took them, jobs are queued in the catalog, where the primary's runner finds
them (within ``poll_s``), and so are cancellations. They do not run jobs, start workers or
clean up, and they die with the primary (even killed with -9); one that exits while the
primary runs is started again.
"""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Sequence

from .settings import Settings

__all__ = ["HttpProcesses", "main"]

log = logging.getLogger("rangefuse.service")

#: The environment variable that hands the primary's settings to the other processes (JSON).
SETTINGS_ENV = "RANGEFUSE_HTTP_PROCESS_SETTINGS"
#: Seconds a process has to finish its requests and store its uploads when the service stops.
_STOP_S = 30.0


class HttpProcesses:
    """The ``settings.http_processes - 1`` other HTTP processes, answering on ``listening``
    (the primary's bound socket). Started by a thread that lives as long as they do (each
    child is killed when that thread ends: ``PR_SET_PDEATHSIG``, as for the Dask processes),
    which also starts again one that exits."""

    def __init__(self, settings: Settings, listening: socket.socket) -> None:
        self.settings = settings
        self._fd = listening.fileno()
        self._procs: list[subprocess.Popen[bytes]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._started = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rangefuse-http", daemon=True)

    def start(self) -> None:
        self._thread.start()
        self._started.wait()

    def _spawn(self) -> subprocess.Popen[bytes]:
        from .cluster import _die_with_parent

        env = {**os.environ, SETTINGS_ENV: self.settings.model_dump_json()}
        return subprocess.Popen(
            [sys.executable, "-m", "rangefuse.service.http_processes", str(self._fd)],
            env=env, stdin=subprocess.DEVNULL, pass_fds=(self._fd,), preexec_fn=_die_with_parent,
        )  # fmt: skip

    def _run(self) -> None:
        with self._lock:
            self._procs = [self._spawn() for _ in range(self.settings.http_processes - 1)]
        self._started.set()
        while not self._stop.wait(0.5):
            with self._lock:
                for i, proc in enumerate(self._procs):
                    if proc.poll() is not None and not self._stop.is_set():
                        log.warning("HTTP process %d exited (%s): starting another",
                                    proc.pid, proc.returncode)  # fmt: skip
                        self._procs[i] = self._spawn()
        # the children's parent thread lives until they have stopped (stop())

    def stop(self) -> None:
        """SIGTERM: each finishes its requests and stores its uploads (SIGKILL after
        :data:`_STOP_S`)."""
        with self._lock:
            self._stop.set()
            procs = list(self._procs)
        for proc in procs:
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=_STOP_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._thread.join()


def main(argv: Sequence[str] | None = None) -> None:
    """One of the other HTTP processes: ``python -m rangefuse.service.http_processes FD``
    with the primary's settings in :data:`SETTINGS_ENV`."""
    import uvicorn

    from ._malloc import tune_malloc
    from ._serve_cli import _log_config
    from .app import create_app

    tune_malloc()
    args = sys.argv[1:] if argv is None else argv
    listening = socket.socket(fileno=int(args[0]))
    settings = Settings.model_validate_json(os.environ[SETTINGS_ENV])
    app = create_app(settings, primary=False)
    config = uvicorn.Config(app, log_level="info", log_config=_log_config())
    uvicorn.Server(config).run(sockets=[listening])


if __name__ == "__main__":
    main()
