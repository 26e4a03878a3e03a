"""Where units run: a local pool of spawned processes (or this process) and a Ray cluster, both behind one small
interface -- submit a unit, wait for some to finish, take a result, close.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

from socnav.experiments.execution import execute_unit
from socnav.experiments.run_directory import RunnerError
from socnav.experiments.units import Unit
from socnav.extras import install_hint

__all__ = ["LocalBackend", "RayBackend", "WorkerLost"]


class WorkerLost(RuntimeError):
    """The process running a unit died (killed, out of memory) before reporting."""


def _worker_init(parent_pid: int) -> None:
    """Pool worker start: exit as soon as the runner is gone, so a killed sweep leaves no unit running."""

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(3)
            time.sleep(0.5)

    threading.Thread(target=watch, name="socnav-parent-watch", daemon=True).start()


class LocalBackend:
    """A pool of spawned processes (one unit each at a time); workers=0 runs units in this process."""

    def __init__(self, workers: int):
        self.workers = workers
        self.pool: Any = None
        self.inline_results: dict[int, dict[str, Any]] = {}

    @property
    def capacity(self) -> int:
        return max(1, self.workers)

    def _pool(self) -> Any:
        if self.pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self.pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                            initializer=_worker_init, initargs=(os.getpid(),))
        return self.pool

    def submit(self, unit: Unit, root: Path) -> Any:
        if self.workers == 0:
            handle = len(self.inline_results)
            self.inline_results[handle] = execute_unit(unit.to_json(), str(root))
            return handle
        return self._pool().submit(execute_unit, unit.to_json(), str(root))

    def wait(self, handles: list[Any], timeout: float) -> list[Any]:
        if self.workers == 0:
            return list(handles)
        from concurrent.futures import FIRST_COMPLETED, wait

        done, _ = wait(handles, timeout=timeout, return_when=FIRST_COMPLETED)
        return list(done)

    def result(self, handle: Any) -> dict[str, Any]:
        if self.workers == 0:
            return self.inline_results.pop(handle)
        from concurrent.futures.process import BrokenProcessPool

        try:
            return handle.result()
        except BrokenProcessPool:
            self._reset()
            raise WorkerLost("the worker process died (killed or out of memory)") from None

    def _reset(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)
            self.pool = None

    def close(self, cancel: bool = False) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=not cancel, cancel_futures=cancel)
            self.pool = None


#: Seconds to wait for a Ray head's port to accept a connection, and for a whole `ray.init` to connect, before
#: giving up on the address.
RAY_CONNECT_TIMEOUT_S = 10.0
RAY_INIT_TIMEOUT_S = 90.0


def _check_ray_connects(address: str, timeout: float = RAY_INIT_TIMEOUT_S) -> None:
    """Connect to `address` once in a child process that is killed after `timeout` seconds: ``ray.init`` retries an
    address where no Ray answers for a long time, inside native code that neither a timeout nor Ctrl-C reaches, so
    the sweep's own ``ray.init`` only runs once a connection is known to succeed. Ctrl-C stops the child too."""
    import subprocess
    import sys

    code = ("import sys, ray; ray.init(address=sys.argv[1], log_to_driver=False, configure_logging=False); "
            "ray.shutdown()")
    try:
        done = subprocess.run([sys.executable, "-c", code, address], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: no Ray answered within {timeout:.0f} s "
                          "(is it the head's address, and does the head run?)") from None
    if done.returncode != 0:
        lines = [line.strip() for line in done.stderr.splitlines() if line.strip()]
        last = lines[-1][:300] if lines else f"exit code {done.returncode}"
        raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: {last}")


def _probe_ray_address(address: str, timeout: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """Refuse a ``host:port`` (or ``ray://host:port``) Ray address at which nothing accepts a connection, within
    `timeout` seconds: ``ray.init`` itself retries such an address without end, inside native code that Ctrl-C
    cannot interrupt. ``auto`` and ``local`` are Ray's to resolve (they fail fast without a cluster)."""
    if address in ("auto", "local"):
        return
    target = address.removeprefix("ray://")
    host, _, port = target.rpartition(":")
    host = host.strip("[]")  # [::1]:6379
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise RunnerError(f"--address {address!r} is not a Ray address; allowed: auto, HOST:PORT (the head's GCS "
                          "port, e.g. 10.0.0.5:6379) or ray://HOST:PORT (Ray Client)")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout) as connection:
            answers = _answers_http2(connection, timeout)
    except OSError as exc:
        reason = (f"no answer within {timeout:.0f} s" if isinstance(exc, TimeoutError)
                  else (exc.strerror or type(exc).__name__).lower())
        raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: nothing accepts connections at "
                          f"{host}:{port} ({reason}); start its head with `ray start --head --port {port}` or check "
                          "the address") from None
    if not answers:
        raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: {host}:{port} accepts connections but "
                          f"does not answer as Ray's (gRPC) server within {timeout:.0f} s; is it the head's port "
                          "(`ray start --head --port PORT`, or ray://HOST:10001 for Ray Client)?")


# What an HTTP/2 client sends first (RFC 9113 section 3.4): the preface, then its SETTINGS frame (empty here).
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


def _answers_http2(connection: socket.socket, timeout: float) -> bool:
    """Whether the server on `connection` speaks HTTP/2, as Ray's gRPC servers (GCS, Ray Client) do: its first
    frame must be SETTINGS (type 4). Skipped (True) with TLS on (``RAY_USE_TLS``), where the handshake comes first.
    """
    if os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true"):
        return True
    connection.settimeout(timeout)
    try:
        connection.sendall(_HTTP2_PREFACE)
        header = b""
        deadline = time.monotonic() + timeout
        while len(header) < 9 and time.monotonic() < deadline:
            chunk = connection.recv(9 - len(header))
            if not chunk:
                break
            header += chunk
    except OSError:
        return False
    return len(header) == 9 and header[3] == 4


class RayBackend:
    """Units as Ray tasks (1 CPU each, retried on worker/node failure); the run directory must be on a filesystem
    every Ray node sees (or the cluster is this machine)."""

    def __init__(self, address: str | None, workers: int, retries: int):
        try:
            import ray
        except ImportError:
            raise RunnerError(f"the ray backend needs Ray: {install_hint('ray')}") from None
        self.ray = ray
        self.started_here = False
        if not ray.is_initialized():
            if address is None:  # a Ray of our own on this machine, quiet
                ray.init(log_to_driver=False, configure_logging=False, include_dashboard=False)
            else:  # an existing cluster ("auto", "host:6379") or a Ray Client address ("ray://host:10001")
                _probe_ray_address(address)
                _check_ray_connects(address)
                try:
                    ray.init(address=address, log_to_driver=False)
                except (ConnectionError, RuntimeError, ValueError) as exc:
                    raise RunnerError(f"cannot connect to the Ray cluster at {address!r}: {exc}") from None
            self.started_here = True
        self.workers = workers
        self.task = ray.remote(num_cpus=1, max_retries=retries, retry_exceptions=False)(execute_unit)

    @property
    def capacity(self) -> int:
        if self.workers > 0:
            return self.workers
        return max(1, int(self.ray.cluster_resources().get("CPU", 1)))

    def submit(self, unit: Unit, root: Path) -> Any:
        return self.task.options(name=unit.id).remote(unit.to_json(), str(root))

    def wait(self, handles: list[Any], timeout: float) -> list[Any]:
        done, _ = self.ray.wait(handles, num_returns=1, timeout=timeout)
        return list(done)

    def result(self, handle: Any) -> dict[str, Any]:
        try:
            return self.ray.get(handle)
        except self.ray.exceptions.RayError as exc:
            raise WorkerLost(f"Ray task failed after retries: {type(exc).__name__}: {exc}") from None

    def close(self, cancel: bool = False) -> None:
        if self.started_here:
            self.ray.shutdown()
