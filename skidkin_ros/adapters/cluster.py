"""Lidar chunks on a Dask cluster: check the address, connect with a deadline, never hang.

Dask's ``Client`` is quick to fail on some mistakes and silent on others, so ``--cluster`` goes
through three checks, each with a message that says what to do:

1. The address, before any work (:func:`check_cluster_address`): a scheduler listens on
   ``tcp://HOST:PORT`` (8786 by default; ``tls://``, ``ws://``, ``wss://``, ``ucx://`` too, and
   ``HOST:PORT`` means tcp). A web address (``http://HOST:8787`` is the dashboard), a host
   without a port or a word that is no address is refused at once, not after the recording has
   been read and then as a ValueError traceback.
2. The connection, within ``CONNECT_TIMEOUT_S`` (:func:`connect`): a port where nothing listens
   fails at once (Dask retries it until its timeout); Dask's own timeout does not cover a port
   where something else listens (a web server, a silent socket): the handshake waits for
   ever, so the client is made in a helper thread and abandoned past the deadline.
3. Workers (:func:`wait_for_workers`, :func:`finished`): a scheduler without workers accepts
   tasks and runs none. The run waits ``WORKER_WAIT_S`` for a first worker, and stops when the
   last one has been gone that long while chunks are pending, naming the scheduler and how to
   start workers.
"""

from __future__ import annotations

import re
import socket
import threading
import time
from typing import Any, Iterator

from skidkin_ros.errors import brief, DataError, ParameterError

__all__ = ['SCHEMES', 'DEFAULT_PORT', 'CONNECT_TIMEOUT_S', 'WORKER_WAIT_S',
           'check_cluster_address', 'connect', 'wait_for_workers', 'finished']

# Dask's network schemes (inproc: the same process only, never a cluster address).
SCHEMES = ('tcp', 'tls', 'ws', 'wss', 'ucx')
DEFAULT_PORT = 8786
CONNECT_TIMEOUT_S = 30.0
WORKER_WAIT_S = 60.0
POLL_S = 0.5
_HOST = re.compile(r'^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?)$')
_START = ('start a scheduler with `dask scheduler` (it prints its tcp:// address) and workers '
          'with `dask worker tcp://HOST:8786 --nthreads 1`')


def check_cluster_address(text: str) -> str:
    """Return a Dask scheduler address as ``scheme://host:port``, or raise ParameterError."""
    address = str(text).strip()
    shown = brief(address)
    scheme, sep, rest = address.partition('://')
    if not sep:
        scheme, rest = 'tcp', address
    scheme = scheme.lower()
    if scheme in ('http', 'https'):
        raise ParameterError(
            f'--cluster {shown} is a web address (the dashboard is http://HOST:8787); the '
            f'scheduler listens on tcp://HOST:{DEFAULT_PORT}: give that address')
    if scheme not in SCHEMES:
        raise ParameterError(f'--cluster {shown}: unknown scheme {brief(scheme)!s}; expected '
                             f'tcp://HOST:PORT (or {", ".join(SCHEMES[1:])})')
    host, colon, port = rest.rpartition(':')
    if not colon or not host:
        host = rest
        hint = (f'add the port: {scheme}://{host}:{DEFAULT_PORT} (the scheduler default)'
                if _HOST.match(host) and '.' in host or host == 'localhost'
                else f'expected tcp://HOST:{DEFAULT_PORT}')
        raise ParameterError(f'--cluster {shown} is not a scheduler address (no port); {hint}')
    if not _HOST.match(host):
        raise ParameterError(f'--cluster {shown}: {brief(host)} is not a host name or an IP '
                             f'address; expected tcp://HOST:{DEFAULT_PORT}')
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ParameterError(f'--cluster {shown}: the port {brief(port)} is not a number '
                             f'from 1 to 65535 (the scheduler default is {DEFAULT_PORT})')
    return f'{scheme}://{host}:{int(port)}'


def connect(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> Any:
    """Return a Dask client of the scheduler at ``address``, or raise DataError by the deadline."""
    try:
        from distributed import Client
    except ImportError as err:
        raise ParameterError('--cluster needs Dask distributed: pip install distributed '
                             '(or the skidkin_ros[cluster] extra)') from err
    address = check_cluster_address(address)
    _probe(address, timeout_s)
    box: dict[str, Any] = {}

    def make() -> None:
        try:
            box['client'] = Client(address, timeout=timeout_s)
        except Exception as err:  # noqa: B902 - reported by the caller's thread
            box['error'] = err

    helper = threading.Thread(target=make, name='skidkin-dask-connect', daemon=True)
    helper.start()
    helper.join(timeout_s + 1.0)
    if 'client' in box:
        return box['client']
    if helper.is_alive():  # a handshake that never ends: something else listens there
        raise DataError(
            f'no Dask scheduler answered at {address} within {timeout_s:g} s (something else '
            f'may listen on that port); check the address, or {_START}')
    err = box.get('error')
    raise DataError(f'cannot reach the Dask scheduler at {address}: '
                    f'{type(err).__name__}: {err}; {_START}') from err


def _probe(address: str, timeout_s: float) -> None:
    """Fail at once where nothing listens (Dask retries a refused connection till its timeout)."""
    scheme, _, rest = address.partition('://')
    if scheme == 'ucx':
        return
    host, _, port = rest.rpartition(':')
    try:
        with socket.create_connection((host.strip('[]'), int(port)), timeout=timeout_s):
            pass
    except OSError as err:
        raise DataError(f'no Dask scheduler at {address}: nothing answers there '
                        f'({err.strerror or err}); {_START}'
                        ) from err


def _workers(client: Any) -> int:
    return len(client.scheduler_info().get('workers', {}))


def wait_for_workers(client: Any, address: str, timeout_s: float = WORKER_WAIT_S) -> int:
    """Return the number of workers once there is one; raise DataError after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        count = _workers(client)
        if count:
            return count
        if time.monotonic() >= deadline:
            raise DataError(f'the Dask scheduler at {address} has no worker (none joined within '
                            f'{timeout_s:g} s): start workers with `dask worker {address} '
                            '--nthreads 1`')
        time.sleep(min(POLL_S, max(deadline - time.monotonic(), 0.0)))


def finished(client: Any, futures: list[Any], address: str,
             worker_wait_s: float = WORKER_WAIT_S) -> Iterator[Any]:
    """Yield the futures as they finish; raise DataError when no worker is left for too long."""
    pending = list(futures)
    alone_since: float | None = None
    next_check = time.monotonic() + POLL_S
    while pending:
        done = [future for future in pending if future.done()]
        if done:
            taken = {id(future) for future in done}
            pending = [future for future in pending if id(future) not in taken]
            alone_since = None
            yield from done
            continue
        time.sleep(0.02)
        now = time.monotonic()
        if now < next_check:
            continue
        next_check = now + POLL_S
        if _workers(client):
            alone_since = None
        elif alone_since is None:
            alone_since = now
        elif now - alone_since > worker_wait_s:
            raise DataError(f'every Dask worker left the scheduler at {address} with '
                            f'{len(pending)} chunk(s) pending; none joined within '
                            f'{worker_wait_s:g} s: start workers with `dask worker {address} '
                            '--nthreads 1`')
