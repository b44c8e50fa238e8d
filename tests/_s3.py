"""A local S3-compatible server for tests (moto's, in a thread of the test process) and a
folder uploaded to it; readers reach it by a pyarrow filesystem URI, as a user's bucket."""

from __future__ import annotations

import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

BUCKET = "robotcar"


@contextmanager
def s3_folder(folder: Path, monkeypatch: pytest.MonkeyPatch, prefix: str = "dl") -> Iterator[str]:
    """The files under ``folder`` uploaded to a fresh local S3 server; yields the URI of their
    copy (``s3://robotcar/dl?endpoint_override=…``). Credentials go by the environment, which
    the ``mine`` subprocesses a test starts inherit."""
    import pyarrow.fs as pafs
    from moto.server import ThreadedMotoServer

    for key, value in (("AWS_ACCESS_KEY_ID", "test"), ("AWS_SECRET_ACCESS_KEY", "test")):
        monkeypatch.setenv(key, value)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    try:
        _reset(host, port)  # moto keeps its buckets per process, not per server: an earlier test's would show
        uri = f"s3://{BUCKET}/{prefix}?endpoint_override=http://{host}:{port}&scheme=http&region=us-east-1"
        fs, base = pafs.FileSystem.from_uri(uri + "&allow_bucket_creation=true")
        fs.create_dir(BUCKET)
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            with fs.open_output_stream(f"{base}/{path.relative_to(folder).as_posix()}") as f:
                f.write(path.read_bytes())
        yield uri
    finally:
        _reset(host, port)
        server.stop()


def _reset(host: str, port: int) -> None:
    """Empty every moto backend (its documented reset endpoint)."""
    urllib.request.urlopen(urllib.request.Request(f"http://{host}:{port}/moto-api/reset", method="POST")).close()
