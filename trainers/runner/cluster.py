"""Where units run: an *executor* runs one function over a list of items and yields ``(index,
result)`` pairs as they finish, in any order, and its caller writes each result down at once.
``InProcess`` is a plain loop here (the default, no Dask needed); ``DaskExecutor`` submits each
item to a ``LocalCluster`` started here (``--cluster local[:N]``) or a running scheduler
(``--scheduler tcp://host:port``), whose scheduler reruns the item of a worker that died (an
item's result depends on the item alone, so the numbers are the same). Dask is the optional extra
``factorq-torch[distributed]`` (without it: a ``ClusterError`` naming it). The choices (one torch
thread per worker process, a node-local kernel cache, fresh task keys, a cluster that loses its
workers as an error): docs/decisions.md, "Sweeps and clusters".
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from factorq_torch.base.validation import MAX_THREADS
from factorq_trainers.runner import options

EXTRA = "distributed"
INSTALL_HINT = (
    f"pip install 'factorq-torch[{EXTRA}]' (in this checkout: pip install -e '.[{EXTRA}]')"
)
DEFAULT_CONNECT_TIMEOUT_S = 10.0
#: The longest wait for a scheduler (a day): a finite bound Dask's timeout parser takes.
MAX_CONNECT_TIMEOUT_S = 86_400.0
#: How long work may wait with no worker in the cluster before the run gives up (a nanny
#: restarts a killed worker within seconds; a cluster whose workers are all gone never finishes).
DEFAULT_WORKER_TIMEOUT_S = 120.0
#: How often a wait for results looks for workers.
WORKER_POLL_S = 1.0
_LOCAL = re.compile(r"^local(?::(\d+))?$")
#: ``--cluster off``: in-process, one unit after another, whatever the command would choose.
OFF = "off"
#: An env step at least this slow (seconds) makes a command's units worth processes ...
SLOW_STEP_S = 1e-3
#: ... when their env steps alone would take at least this long (seconds) in one process.
PROCESSES_AFTER_S = 20.0


class ClusterError(ValueError):
    """A cluster cannot be used: the message says why, in one line."""


@dataclass(frozen=True)
class Where:
    """Where to run: in-process (both None), a local cluster of ``local_workers`` (0: one per
    core), or the scheduler at ``scheduler``; the timeouts in seconds."""

    local_workers: int | None = None  # --cluster local[:N]
    scheduler: str | None = None  # --scheduler tcp://host:port
    connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S  # --connect-timeout
    worker_timeout_s: float = DEFAULT_WORKER_TIMEOUT_S  # --worker-timeout

    def __post_init__(self) -> None:
        if self.local_workers is not None and self.scheduler is not None:
            raise ClusterError("give --cluster or --scheduler, not both")
        if self.local_workers is not None and self.local_workers < 0:
            raise ClusterError(f"--cluster workers={self.local_workers} must be >= 1")
        if self.scheduler is not None and "://" not in self.scheduler:
            raise ClusterError(
                f"--scheduler={self.scheduler!r} is not an address like tcp://host:8786"
            )
        for option, timeout in (
            ("--connect-timeout", self.connect_timeout_s),
            ("--worker-timeout", self.worker_timeout_s),
        ):
            if not (isinstance(timeout, int | float) and 0 < timeout <= MAX_CONNECT_TIMEOUT_S):
                # inf would reach Dask's timeout parser (KeyError), 1e300 would hang for good
                raise ClusterError(
                    f"{option}={timeout!r} is out of range: must be in "
                    f"(0, {MAX_CONNECT_TIMEOUT_S:g}] seconds"
                )

    @property
    def in_process(self) -> bool:
        return self.local_workers is None and self.scheduler is None


def parse_cluster(text: str) -> int:
    """Workers of ``--cluster local[:N]`` (0 for plain ``local``: one per core).

    >>> parse_cluster("local"), parse_cluster("local:2")
    (0, 2)
    """
    match = _LOCAL.match(text)
    if match is not None and match[1] and int(match[1]) > MAX_THREADS:
        raise ClusterError(
            f"--cluster={text!r} is out of range: at most local:{MAX_THREADS} workers"
        )
    if match is None or match[1] == "0":
        raise ClusterError(
            f"--cluster={text!r} is not local, local:N with N >= 1 or off (for a running cluster, "
            f"use --scheduler tcp://host:port)"
        )
    return int(match[1] or 0)


class InProcess:
    """Runs every item here, in order: the default, which needs no Dask."""

    description = "in-process"

    def map(
        self, function: Callable[[Any], Any], items: Sequence[Any], names: Sequence[str]
    ) -> Iterator[tuple[int, Any]]:
        for index, item in enumerate(items):
            yield index, function(item)

    def close(self) -> None:
        pass


#: Tells this process from another: a worker in a process of its own imports this module anew.
_PROCESS_TOKEN = uuid.uuid4().hex


def _worker_setup() -> None:
    """Per worker process: one intra-op thread (the tensors are tiny, the other workers use the
    other cores), a node-local kernel cache (not one NFS folder for every worker)."""
    import torch

    torch.set_num_threads(1)
    user = os.environ.get("USER") or str(os.getuid())
    os.environ.setdefault(
        "FACTORQ_CACHE_DIR", str(Path(tempfile.gettempdir()) / f"factorq_torch-{user}")
    )


def _on_worker(function: Callable[[Any], Any], item: Any, submitter: str) -> Any:
    """What a worker runs: its set-up (idempotent, so a restarted worker gets it too), then the
    item. A worker thread in the submitting process itself (a ``LocalCluster(processes=False)``)
    skips the set-up: the process's thread count and environment are its owner's."""
    if submitter != _PROCESS_TOKEN:
        _worker_setup()
    return function(item)


def _import_distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise ClusterError(f"a Dask cluster needs the '{EXTRA}' extra: {INSTALL_HINT}") from None
    return distributed


class DaskExecutor:
    """Runs items as Dask futures; yields results as they complete. While results are awaited
    the cluster must keep a worker: ``worker_timeout_s`` without any is a ``ClusterError``
    (a cluster that lost every worker would otherwise wait for good, silently)."""

    def __init__(
        self,
        client: Any,
        cluster: Any = None,
        worker_timeout_s: float = DEFAULT_WORKER_TIMEOUT_S,
        left_as_found: _Traces | None = None,
    ) -> None:
        self.client, self.cluster, self.worker_timeout_s = client, cluster, worker_timeout_s
        self._left_as_found = left_as_found
        self._as_completed = _import_distributed().as_completed

    @property
    def workers(self) -> int:
        """The workers in the cluster now (0 when none has joined yet, or all are gone)."""
        info = self.client.scheduler_info(n_workers=0)
        return int(info.get("n_workers", len(info.get("workers", ()))))

    @property
    def description(self) -> str:
        count = self.workers
        return (
            f"Dask scheduler {self.client.scheduler.address} ({count} worker{'s' * (count != 1)})"
        )

    def map(
        self, function: Callable[[Any], Any], items: Sequence[Any], names: Sequence[str]
    ) -> Iterator[tuple[int, Any]]:
        run = uuid.uuid4().hex[:8]  # fresh keys: never a cached result of an earlier call
        futures = {
            self.client.submit(
                _on_worker, function, item, _PROCESS_TOKEN, key=f"{name}-{run}", pure=False
            ): index
            for index, (item, name) in enumerate(zip(items, names, strict=True))
        }
        looked = seen = time.monotonic()

        def watch(left: int) -> None:
            """A ``ClusterError`` once the cluster has had no worker for ``worker_timeout_s``
            (looked at every ``WORKER_POLL_S``) while ``left`` tasks wait."""
            nonlocal looked, seen
            now = time.monotonic()
            if now - looked < WORKER_POLL_S:
                return
            looked = now
            if self.workers:
                seen = now
            elif now - seen >= self.worker_timeout_s:
                raise ClusterError(
                    f"the Dask cluster at {self.client.scheduler.address} has had no worker for "
                    f"{self.worker_timeout_s:g} s, with {left} of {len(futures)} tasks left: "
                    f"start workers and run the command again (finished work is kept), or wait "
                    f"longer with --worker-timeout SECONDS"
                )

        try:
            completed = self._as_completed(futures, loop=self.client.loop)
            while not completed.is_empty():
                if not completed.has_ready():
                    time.sleep(0.02)
                    watch(completed.count())
                    continue
                for future in completed.next_batch(block=False):
                    while True:  # its result may have been lost with its worker meanwhile
                        try:
                            result = future.result(timeout=WORKER_POLL_S)
                            break
                        except TimeoutError:
                            watch(completed.count() + 1)
                    yield futures[future], result
        finally:
            for future in futures:
                future.release()

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        if self._left_as_found is not None:
            self._left_as_found.restore()


class _Traces:
    """What a ``LocalCluster`` leaves in this process, taken before it starts and put back when it
    is closed: its nannies set environment variables here before spawning workers (thread counts,
    ``PYTHONHASHSEED``, ...), its scheduler adds a log handler to its logger. A caller of
    ``open_executor`` (a script, a test) gets its process back as it was."""

    def __init__(self) -> None:
        self.environment = dict(os.environ)
        self.handlers = {name: list(logging.getLogger(name).handlers) for name in _DASK_LOGGERS}

    def restore(self) -> None:
        for name in set(os.environ) - set(self.environment):
            del os.environ[name]
        os.environ.update(self.environment)
        for name, handlers in self.handlers.items():
            logging.getLogger(name).handlers[:] = handlers


#: The loggers a LocalCluster adds handlers to (its scheduler's and its nannies' log records).
_DASK_LOGGERS = ("distributed.scheduler", "distributed.nanny", "distributed.worker")


def _forget_half_made_client(error: BaseException, kind: Any) -> None:
    """Mark the Client whose constructor raised ``error`` closed: when collected, it would try
    to close its connection for 20 s and then print an ignored-exception traceback."""
    frame = error.__traceback__
    while frame is not None:
        made: Any = frame.tb_frame.f_locals.get("self")
        if isinstance(made, kind):
            made.status = "closed"
        frame = frame.tb_next


#: The longest a port that refuses connections at once is tried again (with backoff): long
#: enough for a scheduler that is still starting, short of a long ``--connect-timeout`` spent on
#: a wrong port.
REFUSED_RETRY_S = 10.0
#: A Dask scheduler's first message (its handshake: compression, python and pickle versions) is a
#: few hundred bytes; a peer announcing more is not one (an HTTP reply's first 8 bytes read as
#: a length announce exabytes).
MAX_HANDSHAKE_BYTES = 64 * 1024


def probe_scheduler(address: str, timeout_s: float) -> None:
    """Prove that a Dask scheduler answers at the ``tcp://`` ``address`` within ``timeout_s``,
    before a Client trusts it: a ``ClusterError`` in one line otherwise. A Dask peer sends its
    handshake as soon as the connection is accepted; this reads it on a plain socket under one
    deadline, bounded in size, and decodes it with Dask's own ``unpack_frames`` and ``loads``
    (Dask's own handshake has no timeout, and allocates what another peer's first 8 bytes
    announce). A refused connection is retried with backoff for at most ``REFUSED_RETRY_S``.
    Other schemes (``tls://``, ``inproc://``) are left to the Client."""
    import socket
    import struct

    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.protocol.core import loads
    from distributed.protocol.utils import unpack_frames

    scheme, location = parse_address(address)
    if scheme != "tcp":
        return
    host, port = parse_host_port(location)
    start = time.monotonic()
    deadline = start + timeout_s
    refused_until = start + min(timeout_s, REFUSED_RETRY_S)
    pause, refusals = 0.1, 0

    def left() -> float:
        return deadline - time.monotonic()

    not_dask = f"{address} is not a Dask scheduler"
    while True:
        try:
            connection = socket.create_connection((host, port), timeout=max(left(), 0.001))
            break
        except ConnectionRefusedError:
            refusals += 1
            if time.monotonic() + pause >= refused_until:
                raise ClusterError(
                    f"scheduler {address} refused the connection {refusals} times in "
                    f"{time.monotonic() - start:.1f} s: is a Dask scheduler listening there?"
                ) from None
            time.sleep(pause)
            pause = min(pause * 2, 2.0)
        except (TimeoutError, OSError) as error:
            reason = getattr(error, "strerror", None) or type(error).__name__
            raise ClusterError(
                f"scheduler {address} is unreachable within {timeout_s:g} s ({reason})"
            ) from None

    def receive(count: int) -> bytes:
        data = bytearray()
        while len(data) < count:
            remaining = left()
            if remaining <= 0:
                raise TimeoutError
            connection.settimeout(remaining)
            chunk = connection.recv(min(count - len(data), 65536))
            if not chunk:
                raise ConnectionError("it closed the connection")
            data += chunk
        return bytes(data)

    with connection:
        try:
            (size,) = struct.unpack("Q", receive(8))
            if size > MAX_HANDSHAKE_BYTES:
                raise ClusterError(f"{not_dask}: its first message announces {size} bytes")
            unpacked, more = unpack_frames(receive(size), partial=True)
            frames: list[Any] = list(unpacked)
            if sum(more) > MAX_HANDSHAKE_BYTES:
                raise ClusterError(f"{not_dask}: its first message announces {sum(more)} bytes")
            frames.extend(receive(count) for count in more)
            handshake = loads(frames, deserialize=False)
        except ClusterError:
            raise
        except TimeoutError:
            raise ClusterError(
                f"{not_dask}: it did not answer as one within {timeout_s:g} s (a Dask scheduler "
                f"speaks first)"
            ) from None
        except Exception as error:  # bytes that are not Dask's framing or msgpack
            reason = " ".join(str(error).split())[:120] or type(error).__name__
            raise ClusterError(f"{not_dask}: its first message is not Dask's ({reason})") from None
    if not isinstance(handshake, dict) or "pickle-protocol" not in handshake:
        raise ClusterError(f"{not_dask}: its first message is not a Dask handshake")


def open_executor(where: Where) -> InProcess | DaskExecutor:
    """The executor for ``where``; a ``ClusterError`` (one line) if it cannot be had."""
    if where.in_process:
        return InProcess()
    distributed = _import_distributed()
    if where.scheduler is not None:
        unreachable = (
            f"scheduler {where.scheduler} is unreachable within {where.connect_timeout_s:g} s"
        )
        not_address = f"--scheduler={where.scheduler!r} is not a Dask scheduler address like "
        try:  # before a Client: one that fails in its constructor prints a traceback when
            # collected (its close times out), after the error
            distributed.comm.resolve_address(where.scheduler)
        except (ValueError, TypeError, KeyError) as error:
            raise ClusterError(f"{not_address}tcp://host:8786 ({error})") from None
        except OSError as error:  # a host name that does not resolve
            raise ClusterError(f"{unreachable} ({error})") from None
        probe_scheduler(where.scheduler, where.connect_timeout_s)
        try:
            client = distributed.Client(
                where.scheduler, timeout=f"{where.connect_timeout_s}s", set_as_default=False
            )
        except (OSError, TimeoutError) as error:
            raise ClusterError(f"{unreachable} ({error})") from None
        except (ValueError, TypeError) as error:  # an address resolve_address let through
            _forget_half_made_client(error, distributed.Client)
            raise ClusterError(f"{not_address}tcp://host:8786 ({error})") from None
        return DaskExecutor(client, worker_timeout_s=where.worker_timeout_s)
    left_as_found = _Traces()
    cluster = distributed.LocalCluster(
        n_workers=where.local_workers or os.cpu_count() or 1,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=50,  # CRITICAL only: a killed worker's traceback is expected noise here
    )
    client = distributed.Client(cluster, set_as_default=False)
    return DaskExecutor(
        client, cluster, worker_timeout_s=where.worker_timeout_s, left_as_found=left_as_found
    )


# --------------------------------------------------------------------------------------------
# The command-line options of every command that can run on a cluster


def add_options(parser: argparse.ArgumentParser) -> None:
    """``--cluster``, ``--scheduler``, ``--connect-timeout``, ``--worker-timeout`` (``factorq
    sweep``, every command)."""
    for name, metavar, kind, help_text in (
        ("--cluster", "local[:N]|off", str,
         "Run the units on a Dask LocalCluster of N worker processes started here (plain "
         "'local': one per core). Needs the 'distributed' extra. 'off': in-process, one after "
         "another. (default: in-process, except where a command's env steps slowly enough "
         "for processes to pay: then one per core)"),
        ("--scheduler", "ADDRESS", str,
         "Run the units on the running Dask cluster whose scheduler is at ADDRESS "
         "(tcp://host:8786). Needs the 'distributed' extra."),
        ("--connect-timeout", "SECONDS", options.finite_float,
         f"Give up on --scheduler after this long (at most {MAX_CONNECT_TIMEOUT_S:g}). "
         f"(default: {DEFAULT_CONNECT_TIMEOUT_S:g})"),
        ("--worker-timeout", "SECONDS", options.finite_float,
         "Give up when the cluster has had no worker for this long while work is left "
         f"(finished work is kept; at most {MAX_CONNECT_TIMEOUT_S:g}). "
         f"(default: {DEFAULT_WORKER_TIMEOUT_S:g})"),
    ):  # fmt: skip
        parser.add_argument(
            name, metavar=metavar, type=kind, help=help_text, default=argparse.SUPPRESS
        )


def where_from_args(args: argparse.Namespace) -> Where:
    """Where to run, from ``add_options``' options (a ``ClusterError`` when invalid)."""
    if hasattr(args, "cluster") and hasattr(args, "scheduler"):
        raise ClusterError("give --cluster or --scheduler, not both")
    return Where(
        local_workers=None if getattr(args, "cluster", OFF) == OFF else parse_cluster(args.cluster),
        scheduler=getattr(args, "scheduler", None),
        connect_timeout_s=getattr(args, "connect_timeout", DEFAULT_CONNECT_TIMEOUT_S),
        worker_timeout_s=getattr(args, "worker_timeout", DEFAULT_WORKER_TIMEOUT_S),
    )


def _cores() -> int:
    """The cores this process may run on (its affinity, where the system says)."""
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity is not None else os.cpu_count() or 1


def default_workers(step_s: float, steps: int, units: int) -> int:
    """How many processes a command's ``units`` take by default, each stepping an env
    ``steps`` times at ``step_s`` seconds a step: one per core (at most one per unit) where the
    env is slow (``SLOW_STEP_S``) and the steps alone would take ``PROCESSES_AFTER_S`` in one
    process, else 1 (in-process: starting processes costs seconds).

    >>> default_workers(0.005, 10_000, 1), default_workers(0.0001, 10_000, 6)
    (1, 1)
    """
    cores = _cores()
    slow = step_s >= SLOW_STEP_S and step_s * steps * units >= PROCESSES_AFTER_S
    return min(cores, units) if slow and units > 1 and cores > 1 else 1
