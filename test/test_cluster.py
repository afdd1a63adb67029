"""``--cluster``: the address checked first, a deadline on the connection, workers waited for.

On Dask's local cluster and on real sockets (a web server, a silent listener); each case takes
seconds (the deadlines are shortened).
"""

import http.server
from pathlib import Path
import socket
import subprocess
import sys
import threading
import time

import pytest
from skidkin_ros.adapters.cluster import (check_cluster_address, connect, finished,
                                          wait_for_workers)
from skidkin_ros.cli.main import main
from skidkin_ros.errors import DataError, ParameterError

distributed = pytest.importorskip('distributed')


@pytest.mark.parametrize('text, words', [
    ('http://127.0.0.1:8787', 'is a web address'),
    ('https://cluster.example.org', 'is a web address'),
    ('127.0.0.1', 'add the port: tcp://127.0.0.1:8786'),
    ('garbage', 'no port'),
    ('tcp://127.0.0.1:99999', 'not a number from 1 to 65535'),
    ('tcp://127.0.0.1:x', 'not a number from 1 to 65535'),
    ('tcp://bad host:8786', 'not a host name'),
    ('ftp://127.0.0.1:8786', 'unknown scheme'),
])
def test_an_address_that_is_no_scheduler_address_is_refused_saying_what_to_give(text, words):
    with pytest.raises(ParameterError, match=words):
        check_cluster_address(text)


@pytest.mark.parametrize('text, address', [
    ('tcp://10.0.0.5:8786', 'tcp://10.0.0.5:8786'), ('10.0.0.5:8786', 'tcp://10.0.0.5:8786'),
    ('TLS://sched.lab:8786', 'tls://sched.lab:8786'), ('[::1]:8786', 'tcp://[::1]:8786'),
    ('localhost:8786', 'tcp://localhost:8786'),
])
def test_scheduler_addresses_are_taken(text, address):
    assert check_cluster_address(text) == address


@pytest.mark.parametrize('text', ['http://127.0.0.1:8787', '127.0.0.1', 'garbage'])
def test_groundtruth_checks_the_address_before_reading_the_recording(tmp_path, capsys, text):
    # the recording does not even exist: the address is refused first, exit 2, no traceback
    started = time.monotonic()
    with pytest.raises(SystemExit) as exit_:
        main(['groundtruth', str(tmp_path / 'no_bag'), '--out', str(tmp_path / 'gt.csv'),
              '--cluster', text])
    assert exit_.value.code == 2 and time.monotonic() - started < 5.0
    err = capsys.readouterr().err
    assert 'argument --cluster' in err and 'Traceback' not in err and 'ValueError' not in err


def test_a_port_where_something_else_listens_times_out_with_a_clear_error():
    web = http.server.ThreadingHTTPServer(('127.0.0.1', 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=web.serve_forever, daemon=True).start()
    silent = socket.socket()
    silent.bind(('127.0.0.1', 0))
    silent.listen(5)
    try:
        for port in (web.server_address[1], silent.getsockname()[1]):
            started = time.monotonic()
            with pytest.raises(DataError, match='no Dask scheduler answered .* within 1 s'):
                connect(f'tcp://127.0.0.1:{port}', timeout_s=1.0)
            assert time.monotonic() - started < 5.0   # it hung past Dask's own 30 s timeout
    finally:
        web.shutdown()
        silent.close()


def test_a_scheduler_without_workers_is_said_not_waited_on_for_ever():
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None,
                                  protocol='tcp://') as lc:
        client = connect(lc.scheduler_address, timeout_s=10.0)
        try:
            started = time.monotonic()
            with pytest.raises(DataError, match='has no worker .*dask worker tcp://'):
                wait_for_workers(client, lc.scheduler_address, timeout_s=1.0)
            assert time.monotonic() - started < 5.0
        finally:
            client.close()


def test_workers_that_all_leave_mid_run_stop_the_run_with_a_clear_error():
    # the only worker (a `dask worker` process) dies while a chunk runs: the run stops
    dask = Path(sys.executable).with_name('dask')
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None,
                                  protocol='tcp://') as lc:
        worker = subprocess.Popen([str(dask), 'worker', lc.scheduler_address, '--no-nanny',
                                   '--nthreads', '1', '--no-dashboard'],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        client = connect(lc.scheduler_address, timeout_s=10.0)
        try:
            assert wait_for_workers(client, lc.scheduler_address, timeout_s=30.0) == 1
            quick = client.submit(sum, [1, 2], pure=False)
            slow = client.submit(time.sleep, 60, pure=False)
            got = []
            started = time.monotonic()
            with pytest.raises(DataError, match='every Dask worker left .* 1 chunk'):
                for future in finished(client, [quick, slow], lc.scheduler_address,
                                       worker_wait_s=1.0):
                    got.append(future.result())
                    worker.kill()
            assert got == [3] and time.monotonic() - started < 20.0
        finally:
            worker.kill()
            worker.wait()
            client.close()


def test_a_port_where_nothing_listens_fails_at_once():
    closed = socket.socket()
    closed.bind(('127.0.0.1', 0))
    port = closed.getsockname()[1]
    closed.close()
    started = time.monotonic()
    with pytest.raises(DataError,
                       match='no Dask scheduler at tcp://127.0.0.1:.*nothing answers'):
        connect(f'127.0.0.1:{port}', timeout_s=30.0)
    assert time.monotonic() - started < 5.0   # Dask retried it for its whole 30 s timeout
