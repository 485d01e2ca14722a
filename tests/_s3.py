"""A local S3-compatible server for tests: moto in server mode on 127.0.0.1.

No AWS account and no network: ``moto.server.ThreadedMotoServer`` serves the
S3 API from a thread of the test process (or ``moto_server`` from a
subprocess, see :func:`moto_subprocess`), and s3fs talks to it through
``storage_options`` (or the environment of a child process,
:meth:`S3Server.child_env`). Fixtures, for any test module::

    from _s3 import s3_server, s3_url  # noqa: F401  (pytest fixtures)

    def test_something(s3_url, s3_server):
        storage = ZarrStorage(s3_url, 1000, storage_options=s3_server.storage_options)

``s3_server`` is one server per test session; ``s3_url`` is a fresh bucket
with a store URL in it (``s3://<bucket>/memory.zarr``), so tests never see
each other's objects. Tests that need it are skipped with the reason when
moto or s3fs is not installed.
"""
from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field

import pytest

__all__ = ["S3Server", "s3_server", "s3_url", "moto_subprocess", "new_bucket"]


@dataclass
class S3Server:
    """Where a running local S3 server listens, and how to reach it.

    Args:
        endpoint (str): ``http://127.0.0.1:<port>``.
    """

    endpoint: str
    _stop: object = field(default=None, repr=False)

    @property
    def storage_options(self) -> dict:
        """What to pass as ``ZarrStorage(..., storage_options=...)`` (fsspec / s3fs options)."""
        return {
            "client_kwargs": {"endpoint_url": self.endpoint, "region_name": "us-east-1"},
            "key": "testing",
            "secret": "testing",
        }

    def child_env(self) -> dict:
        """Environment variables for a child process (s3fs reads them without ``storage_options``)."""
        env = dict(os.environ)
        env.update(
            AWS_ACCESS_KEY_ID="testing",
            AWS_SECRET_ACCESS_KEY="testing",
            AWS_DEFAULT_REGION="us-east-1",
            AWS_ENDPOINT_URL=self.endpoint,
            AWS_EC2_METADATA_DISABLED="true",
        )
        return env

    def client(self):
        import boto3

        return boto3.client(
            "s3", endpoint_url=self.endpoint, aws_access_key_id="testing",
            aws_secret_access_key="testing", region_name="us-east-1",
        )

    def stop(self) -> None:
        if self._stop is not None:
            self._stop()
            self._stop = None


def new_bucket(server: S3Server, prefix: str = "mem") -> str:
    """Creates an empty bucket with a unique name; returns the name."""
    name = f"{prefix}-{uuid.uuid4().hex[:12]}"
    server.client().create_bucket(Bucket=name)
    return name


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def moto_subprocess(port: int | None = None, timeout: float = 30.0) -> S3Server:
    """Starts ``moto_server`` in a subprocess (killable independently of the test process).

    Returns an :class:`S3Server` whose ``stop()`` terminates the process.
    """
    port = port or _free_port()
    exe = os.path.join(os.path.dirname(sys.executable), "moto_server")
    cmd = [exe] if os.path.exists(exe) else [sys.executable, "-m", "moto.server"]
    proc = subprocess.Popen([*cmd, "-H", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                break
        except OSError:
            if proc.poll() is not None:
                raise RuntimeError(f"moto_server exited with status {proc.returncode}") from None
            time.sleep(0.1)
    else:
        proc.kill()
        raise RuntimeError(f"moto_server did not listen on 127.0.0.1:{port} within {timeout} s")

    def stop():
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()

    return S3Server(f"http://127.0.0.1:{port}", stop)


def threaded_server() -> S3Server:
    """Starts moto's S3 server in a thread of this process."""
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one log line per request otherwise
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    return S3Server(f"http://{host}:{port}", server.stop)


@pytest.fixture(scope="session")
def s3_server():
    """One moto S3 server (in a thread) for the test session."""
    pytest.importorskip("moto.server", reason="moto[server] is needed for the object-store tests")
    pytest.importorskip("s3fs", reason="s3fs is needed for s3:// stores")
    server = threaded_server()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def s3_url(s3_server):
    """A store URL in a new, empty bucket: ``s3://<bucket>/memory.zarr``."""
    return f"s3://{new_bucket(s3_server)}/memory.zarr"
