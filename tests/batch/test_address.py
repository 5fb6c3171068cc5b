"""``batch run --address``: an address where no Ray runs is a one-line error within seconds.

``ray.init(address=HOST:PORT)`` retries an address where nothing listens for many minutes, so a
typo in the port or a head that was never started looked like a hung command. The driver now
probes the address with a bounded TCP connect first (``--connect-timeout``).

A listening service that is not Ray (an HTTP server, a socket that never answers) passed that
probe, and ``ray.init`` then retried it for minutes (over 300 s with Ray 2.60). The driver now
opens HTTP/2 on the connection as a gRPC client does and names a service that does not answer
as one (at once, or at ``--connect-timeout`` when it stays silent).
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from app.batch.driver import check_reachable, split_address
from app.cli import CliError, main
from tests.batch.conftest import make_data


def _closed_port() -> int:
    """A local port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_split_address() -> None:
    assert split_address("auto") is None
    assert split_address(" AUTO ") is None
    assert split_address("head.lab:6379") == ("head.lab", 6379)
    assert split_address("ray://10.0.0.5:10001") == ("10.0.0.5", 10001)
    assert split_address("[::1]:6379") == ("::1", 6379)
    # Ray's other addresses are Ray's to read: not probed, not refused
    assert split_address("local") is None and split_address("Local") is None
    assert split_address("anyscale://my-cluster") is None
    for bad in ("head.lab", ":6379", "head:", "head:port", "head:0", "head:70000", ""):
        with pytest.raises(ValueError, match="--address must be 'auto' or HOST:PORT"):
            split_address(bad)


def test_an_unreachable_address_is_one_line_and_quick(tmp_path: Path) -> None:
    """A closed port: refused at once, a one-line error naming the address and what to check;
    ``ray.init`` is never reached (before the fix this command hung for many minutes)."""
    d = make_data(tmp_path / "data", 1)
    (d / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    port = _closed_port()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RAY_ADDRESS": ""}
    out = subprocess.run(
        [sys.executable, "-m", "app", "batch", "run", str(d / "m.csv"), "--out",
         str(tmp_path / "b"), "--address", f"127.0.0.1:{port}", "--quiet"],
        capture_output=True, text=True, cwd=Path(__file__).parents[2], env=env, timeout=120)
    assert out.returncode == 2, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, out.stderr
    msg = lines[0]
    assert msg.startswith(f"lenslesscam batch: error: cannot reach the Ray cluster at "
                          f"127.0.0.1:{port}: "), msg
    assert "connection refused" in msg
    assert f"ray start --head --port={port}" in msg and "--connect-timeout" in msg
    # refused before the batch folder is made (it was left half-made, "interrupted")
    assert not (tmp_path / "b").exists()


def test_an_address_that_does_not_answer_times_out(monkeypatch: pytest.MonkeyPatch) -> None:
    """A dropped SYN (a firewall, a host that is down) ends at the timeout, which is named."""
    seen = {}

    def no_answer(addr, timeout=None, **_kw):
        seen["timeout"] = timeout
        raise TimeoutError("timed out")

    monkeypatch.setattr(socket, "create_connection", no_answer)
    with pytest.raises(CliError, match=r"^cannot reach the Ray cluster at head\.lab:6379: no "
                                       r"answer from .*:6379 within 2\.5 s; check"):
        check_reachable("head.lab:6379", 2.5)
    assert seen["timeout"] == 2.5
    # `auto` is what Ray finds on this machine (Ray's own reading, stood in for here: a Ray
    # of another test may run on this machine): none, said before anything is written
    services = pytest.importorskip("ray._private.services")

    def none_here(address):
        raise ConnectionError("Could not find any running Ray instance. Please specify the one "
                              "to connect to by setting `--address` flag or `RAY_ADDRESS`")

    monkeypatch.setattr(services, "canonicalize_bootstrap_address", none_here)
    with pytest.raises(CliError, match=r"^cannot join the Ray cluster at auto: Could not find "
                                       r"any running Ray instance; start one"):
        check_reachable("auto", 2.5)
    # one found: probed as HOST:PORT is
    monkeypatch.setattr(services, "canonicalize_bootstrap_address", lambda a: "head.lab:6379")
    seen.clear()
    with pytest.raises(CliError, match=r"^cannot reach the Ray cluster at auto: no answer"):
        check_reachable("auto", 2.5)
    assert seen["timeout"] == 2.5


def test_a_bad_address_is_refused_before_anything_is_written(tmp_path: Path, capsys) -> None:
    d = make_data(tmp_path / "data", 1)
    (d / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    rc = main(["batch", "run", str(d / "m.csv"), "--out", str(tmp_path / "b"),
               "--address", "head.lab"])
    assert rc == 2
    assert "--address must be 'auto' or HOST:PORT" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()
    with pytest.raises(SystemExit) as exc:
        main(["batch", "run", str(d / "m.csv"), "--out", str(tmp_path / "b"),
              "--address", "head.lab:6379", "--connect-timeout", "0"])
    assert exc.value.code == 2
    assert "--connect-timeout: must be a finite number > 0" in capsys.readouterr().err


class _Quiet(BaseHTTPRequestHandler):
    """An HTTP/1 server that serves nothing (it answers every request with an error)."""

    def log_message(self, *args) -> None:
        pass


@contextmanager
def _http_server():
    # every interface: the probe goes where Ray would connect (this machine's IP for 127.0.0.1)
    srv = ThreadingHTTPServer(("0.0.0.0", 0), _Quiet)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    try:
        yield int(srv.server_address[1])
    finally:
        srv.shutdown()
        srv.server_close()
        t.join(5)


@contextmanager
def _tcp_server(answer: bytes | None):
    """Accept connections; send ``answer`` on each (None: never a byte), keep it open."""
    srv = socket.socket()
    srv.bind(("0.0.0.0", 0))
    srv.listen(8)
    srv.settimeout(0.2)
    conns: list[socket.socket] = []
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            try:
                c, _ = srv.accept()
            except OSError:
                continue
            conns.append(c)
            if answer is not None:
                c.sendall(answer)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        yield int(srv.getsockname()[1])
    finally:
        stop.set()
        t.join(5)
        for c in conns:
            c.close()
        srv.close()


#: what a gRPC server sends first: a SETTINGS frame (one setting) on stream 0
_SETTINGS = bytes([0, 0, 6, 4, 0, 0, 0, 0, 0]) + bytes([0, 3, 0, 0, 0, 100])


def test_a_service_that_is_not_ray_is_named_quickly() -> None:
    """An HTTP server, a port that closes at once and one that never answers are each one
    line naming the address and saying it does not answer as a Ray cluster (GCS); a server
    that answers as gRPC (as the GCS does) passes."""
    with _http_server() as port:
        t0 = time.monotonic()
        with pytest.raises(CliError) as err:
            check_reachable(f"127.0.0.1:{port}", 5.0)
        assert time.monotonic() - t0 < 3.0
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"127.0.0.1:{port} does not answer as a Ray cluster (GCS): ")
    assert f":{port} accepts connections but answered " in msg and "not HTTP/2" in msg
    assert "the Ray head's GCS port (default 6379" in msg
    with _tcp_server(None) as port:
        t0 = time.monotonic()
        with pytest.raises(CliError, match=r"does not answer as a Ray cluster \(GCS\): .* did not "
                                           r"answer a gRPC \(HTTP/2\) client within 1 s "
                                           r"\(--connect-timeout waits longer\)"):
            check_reachable(f"127.0.0.1:{port}", 1.0)
        assert time.monotonic() - t0 < 3.0
    with _tcp_server(b"SSH-2.0-OpenSSH_9.6\r\n") as port:
        with pytest.raises(CliError, match=re.escape("answered 'SSH-2.0-O'..., not HTTP/2")):
            check_reachable(f"127.0.0.1:{port}", 5.0)
    with _tcp_server(_SETTINGS) as port:
        check_reachable(f"127.0.0.1:{port}", 5.0)  # a gRPC server: left to ray.init


def test_batch_run_on_an_http_server_is_one_line_within_seconds(tmp_path: Path) -> None:
    """`batch run --address HOST:PORT` on a listening HTTP server: ray.init retried it for
    minutes; now one line naming the address, before Ray is started, within seconds."""
    d = make_data(tmp_path / "data", 1)
    (d / "m.csv").write_text("measurement,psf,method\nmeas/m00.npy,psf.npy,fista\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RAY_ADDRESS": ""}
    with _http_server() as port:
        t0 = time.monotonic()
        out = subprocess.run(
            [sys.executable, "-m", "app", "batch", "run", str(d / "m.csv"), "--out",
             str(tmp_path / "b"), "--address", f"127.0.0.1:{port}", "--quiet"],
            capture_output=True, text=True, cwd=Path(__file__).parents[2], env=env, timeout=60)
        wall = time.monotonic() - t0
    assert out.returncode == 2, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert lines == [ln for ln in lines if ln.startswith("lenslesscam batch: error: ")], lines
    assert len(lines) == 1 and lines[0].startswith(
        f"lenslesscam batch: error: 127.0.0.1:{port} does not answer as a Ray cluster (GCS): ")
    assert wall < 30, wall  # the interpreter and Ray's import take most of it
    # refused before the batch folder is made (it was left half-made, "interrupted")
    assert not (tmp_path / "b").exists()
