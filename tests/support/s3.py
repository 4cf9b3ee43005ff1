"""A local S3 server for the object-storage tests (moto's, on a free port) and the files of a run compared
through it (tests/pipeline/batch/test_object_storage.py, test_ray_backend.py). Callers skip first where s3fs
or moto is missing (``pytest.importorskip``): they are imported only when a server starts."""

import contextlib

import pytest

CREDENTIALS = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}


@contextlib.contextmanager
def s3_server():
    """A local S3 server (moto's, on a free port), empty, the credentials in this process's environment while it
    runs: yields (storage options pointing at it, an s3fs file system on it). Moto keeps its buckets in the
    process, whatever server serves them: they are emptied when the server starts and when it stops."""
    import s3fs
    from moto import server as moto_server

    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    env = pytest.MonkeyPatch()
    for k, v in CREDENTIALS.items():  # for the spawned workers too; no profile of the machine's
        env.setenv(k, v)
    env.delenv("AWS_PROFILE", raising=False)
    try:
        host, port = (server.get_host_and_port() if hasattr(server, "get_host_and_port")  # moto >= 5.0.x
                      else ("127.0.0.1", server._server.server_port))
        options = {"endpoint_url": f"http://{host}:{port}", "key": "testing", "secret": "testing"}
        _reset(options)
        yield options, s3fs.S3FileSystem(**options, use_listings_cache=False, skip_instance_cache=True)
        _reset(options)
    finally:
        env.undo()
        server.stop()


def _reset(options):
    """Empty moto's buckets (its server's reset call)."""
    import urllib.request

    with urllib.request.urlopen(urllib.request.Request(options["endpoint_url"] + "/moto-api/reset",
                                                       method="POST"), timeout=10) as answer:
        assert answer.status == 200


def upload(fs, folder, url):
    """Copy a local folder to ``url``, an object a file (put side by side: s3fs's batch of puts)."""
    fs.pipe({url[len("s3://"):] + "/" + p.relative_to(folder).as_posix(): p.read_bytes()
             for p in sorted(folder.rglob("*")) if p.is_file()})


def objects(fs, url) -> dict:
    """Every object under ``url``: its bytes, by its path below ``url``."""
    base = url[len("s3://"):]
    return {k[len(base) + 1:]: fs.cat_file(k) for k in fs.find(base)}


def plys(folder) -> dict:
    """Every PLY file under a local ``folder``: its bytes, by its path below ``folder``."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*.ply"))}
