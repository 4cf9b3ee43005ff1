"""Scans and results on object storage (``s3://``, ``gs://``, ... through fsspec): docs/batch.md, "Scans on S3".

Every reader and writer of ringscan works on local files (bounded reads, header checks
before decoding, atomic writes). A scan or an output folder given as a URL is *staged*
in a private temporary folder (:func:`stage`), so those readers and writers run
unchanged and give the same bytes:

1. the scan's objects are listed once (one request per 1000 objects): their sizes and
   modification times stand in for the local files' in the freshness hash
   (``reconstruct.freshness``), so whether a scan is done is decided without
   downloading its frames;
2. scan.json, the rig file and the packed stores' zarr.json (both cameras' of a
   two-camera view) are downloaded (each
   bounded as a local read is, :mod:`.limits`) and checked by the usual loader; the
   frames (image files, or a store's chunks) are downloaded only when a view is to be
   computed (:meth:`Staged.fetch_frames`), each refused before the download when it is
   larger than ringscan reads, and given its object's modification time;
3. the output folder's objects (report.json, the PLYs, fused results) are downloaded,
   the run resumes there as locally, and :meth:`Staged.commit` uploads what changed,
   each object whole (a PUT, or a multipart upload that appears only once complete),
   ``report.json`` last: it lists a view only once the view's PLY is stored, so a
   worker killed at any point leaves no object half-written and nothing listed that is
   not whole.

Errors name the URL, never the temporary folder: a missing bucket, refused credentials,
an endpoint that does not answer (bounded: :data:`S3_DEFAULTS`) are one line each
(:class:`StorageError`). Local paths and ``file://`` URLs are not staged.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import posixpath
import re
import secrets
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from ringscan.pipeline.formats.atomic import _process_alive, atomic_write_bytes
from ringscan.pipeline.formats.errors import FormatError, RingscanError
from ringscan.pipeline.formats.limits import MAX_JSON_BYTES

log = logging.getLogger(__name__)

__all__ = ["MAX_OBJECT_BYTES", "S3_DEFAULTS", "LIST_THREADS", "StorageError", "StorageOptionError", "check_url",
           "is_url", "local_path", "join_location", "parse_storage_options", "filesystem", "storage_error",
           "check_location", "find_scan_urls", "write_json_to", "Staged", "stage"]

MAX_OBJECT_BYTES = 1 << 30
"""Largest object downloaded as a frame or an output (1 GiB; a 200-megapixel 16-bit frame
is 400 MB): refused before the download, naming the URL."""

S3_DEFAULTS = {"config_kwargs": {"connect_timeout": 10, "read_timeout": 60,
                                 "retries": {"max_attempts": 3, "mode": "standard"}},
               "use_listings_cache": False}
"""s3fs options ringscan sets unless given (``--storage-option``): an endpoint that does not
answer fails within seconds, not minutes; listings are never served from a cache."""

_URL_RE = re.compile(r"^(?P<scheme>[A-Za-z][A-Za-z0-9+.\-]*)://")
_STAGE_RE = re.compile(r"^ringscan-stage-(?P<pid>\d+)-[0-9a-f]{8}$")
_filesystems: dict = {}


class StorageError(FormatError):
    """Object storage refused or could not serve a request (one line naming the URL)."""


def is_url(location) -> bool:
    """Whether ``location`` is a URL of object storage (``s3://``, ``gs://``, ``memory://`` ...); a local path
    and a ``file://`` URL are not."""
    m = _URL_RE.match(os.fspath(location)) if isinstance(location, (str, os.PathLike)) else None
    return m is not None and m["scheme"].lower() != "file"


def check_url(url: str) -> str:
    """Refuse a URL that names no bucket (``s3://``, ``s3:///x``): returns ``url``.

    Raises:
        StorageError: naming the URL.
    """
    m = _URL_RE.match(url)
    if m is None or not url[m.end():].strip("/") or url[m.end():].startswith("/"):
        raise StorageError(url, "names no bucket: expected SCHEME://BUCKET/PATH (e.g. s3://scans/2024)")
    return url


def local_path(location) -> Path:
    """A local path or ``file://`` URL as a Path."""
    text = os.fspath(location)
    return Path(text[len("file://"):]) if text.lower().startswith("file://") else Path(text)


def join_location(base: str, rel: str) -> str:
    """``base/rel`` for a URL."""
    return base.rstrip("/") + "/" + rel.strip("/") if rel else base


def parse_storage_options(items) -> dict:
    """``KEY=VALUE`` strings (``--storage-option``) as fsspec options: VALUE as JSON where it parses (numbers,
    true, objects), else a string; a dotted KEY nests (``config_kwargs.connect_timeout=5``).

    Raises:
        ValueError: an item without ``=`` or with an empty key.
    """
    out: dict = {}
    for item in items or ():
        key, sep, value = str(item).partition("=")
        key = key.strip()
        if not sep or not key or any(not k for k in key.split(".")):
            raise ValueError(f"--storage-option {item!r}: expected KEY=VALUE (e.g. endpoint_url=http://host:9000)")
        try:
            v = json.loads(value)
        except ValueError:
            v = value
        *parents, last = key.split(".")
        d = out
        for k in parents:
            d = d.setdefault(k, {})
            if not isinstance(d, dict):
                raise ValueError(f"--storage-option {item!r}: {k} is already a value, not a group")
        d[last] = v
    return out


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


CLOUD_INSTALL = "pip install fsspec s3fs (or pip install '.[cloud]' in ringscan's source tree)"
"""How to get the packages URLs need (ringscan is not on a package index: no ``ringscan[cloud]`` there)."""


def filesystem(url: str, options: dict | None = None):
    """The fsspec file system of ``url`` (one per protocol and options in a process) and the path in it.

    Raises:
        StorageError: fsspec, or the package for the protocol (s3fs, gcsfs), is not installed, or the
            options are not the file system's.
    """
    check_url(url)
    scheme = _URL_RE.match(url)["scheme"].lower()
    try:
        import fsspec
    except ImportError:
        raise StorageError(url, f"reading and writing URLs needs fsspec (and s3fs for s3://): {CLOUD_INSTALL}") from None
    opts = _merge(S3_DEFAULTS, options or {}) if scheme in ("s3", "s3a") else dict(options or {})
    key = (scheme, json.dumps(opts, sort_keys=True, default=str))
    fs = _filesystems.get(key)
    if fs is None:
        try:
            fs = fsspec.filesystem(scheme, **opts)
        except ImportError as e:  # fsspec names the package of the protocol (gcsfs, adlfs)
            hint = CLOUD_INSTALL if scheme in ("s3", "s3a") else "pip install the package it names"
            raise StorageError(url, f"{' '.join(str(e).split())} ({hint})") from None
        except (TypeError, ValueError) as e:
            text = " ".join(str(e).split())
            option = storage_error(url, e)
            if isinstance(option, StorageOptionError):
                raise option from None
            if text.startswith("Protocol not known"):
                raise StorageError(url, f"unknown protocol {scheme}:// (fsspec knows s3://, gs://, az://, "
                                        "file://, ...)") from None
            raise StorageError(url, f"bad storage options for {scheme}:// ({text})") from None
        _filesystems[key] = fs
    return fs, fs._strip_protocol(url).rstrip("/")


class StorageOptionError(ValueError):
    """A storage option (``--storage-option``) the file system does not take: a usage error (exit status 2)."""


def storage_error(url: str, e: BaseException) -> StorageError | StorageOptionError:
    """One line for an error of object storage, naming ``url``: a missing bucket or object, refused
    credentials, an endpoint that cannot be reached, or the library's own words; a storage option the
    file system does not take (s3fs passes unknown ones on to its session: a ``TypeError`` at the first
    request) is a :class:`StorageOptionError` naming the option."""
    if isinstance(e, StorageError):
        return e
    m = re.search(r"unexpected keyword argument '([^']+)'", str(e)) if isinstance(e, TypeError) else None
    if m:
        scheme = (_URL_RE.match(url) or {"scheme": "?"})["scheme"]
        return StorageOptionError(f"--storage-option {m[1]}: not an option of the {scheme}:// file system "
                                  f"(docs/batch.md lists the usual ones; {' '.join(str(e).split())[:200]})")
    text = " ".join(str(e).split())
    low = text.lower()
    name = type(e).__name__
    if isinstance(e, FileNotFoundError):
        why = "bucket not found" if "bucket" in low else "not found"
    elif isinstance(e, PermissionError) or any(w in low for w in ("access denied", "accessdenied", "forbidden",
                                                                   "invalidaccesskeyid", "signaturedoesnotmatch",
                                                                   "security token")):
        why = f"access denied: check the credentials and the bucket's permissions ({text[:200]})"
    elif name == "NoCredentialsError" or "unable to locate credentials" in low:
        why = ("no credentials found: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, a profile, or "
               "--storage-option key=... --storage-option secret=... (docs/batch.md)")
    elif (isinstance(e, (ConnectionError, TimeoutError)) or "connect" in name.lower() or "timeout" in name.lower()
          or "could not connect" in low):
        why = f"cannot reach the storage service ({text[:200]})"
    else:
        why = f"{name}: {text[:300] or '(no message)'}"
    return StorageError(url, why)


@contextlib.contextmanager
def _mapped(url: str):
    """Turn any error of the storage library inside the block into a :class:`StorageError` naming ``url``."""
    try:
        yield
    except (FormatError, StorageOptionError):
        raise
    except Exception as e:  # noqa: BLE001 - s3fs, botocore, aiohttp, gcsfs: their errors share no base class
        raise storage_error(url, e) from None


def check_location(url: str, options: dict | None = None, *, what: str = "output folder") -> None:
    """Check that ``url``'s bucket (its first path component) is there and answers, before anything is written.

    Raises:
        StorageError: naming the URL (bucket not found, access denied, endpoint unreachable).
    """
    fs, path = filesystem(url, options)
    bucket = path.split("/")[0]
    if not bucket:
        raise StorageError(url, f"cannot be the {what}: no bucket in the URL")
    try:
        fs.info(bucket)  # a missing bucket, refused credentials or a silent endpoint: here, not mid-batch
    except FileNotFoundError:
        raise StorageError(url, f"cannot be the {what}: bucket {bucket!r} not found") from None
    except Exception as e:  # noqa: BLE001 - the storage library's errors share no base class
        raise storage_error(url, e) from None


def _listing(fs, path: str, url: str) -> dict[str, dict]:
    """Every object below ``path``: its path relative to ``path`` -> its info."""
    with _mapped(url):
        found = fs.find(path, detail=True) if path else {}
    out = {}
    prefix = path.rstrip("/") + "/"
    for name, info in found.items():
        if name.startswith(prefix) and info.get("type", "file") != "directory":
            out[name[len(prefix):]] = info
    return out


def _mtime_ns(info: dict) -> int:
    """An object's modification time in ns (0 when the store gives none)."""
    import datetime as dt

    for k in ("LastModified", "last_modified", "mtime", "updated", "modified", "created"):
        v = info.get(k)
        if isinstance(v, str):
            try:
                v = dt.datetime.fromisoformat(v.replace("Z", "+00:00"))
            except ValueError:
                continue
        if isinstance(v, dt.datetime):
            if v.tzinfo is None:
                v = v.replace(tzinfo=dt.timezone.utc)
            return int(v.timestamp()) * 1_000_000_000 + v.microsecond * 1000
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return int(v * 1e9)
    return 0


def _size(info: dict) -> int:
    return int(info.get("size", info.get("Size", 0)) or 0)


LIST_THREADS = 16
"""Folders (prefixes) listed at a time while a batch searches object storage for scans."""


def find_scan_urls(root: str, options: dict | None = None, *, skipped: list | None = None) -> list[str]:
    """Scan folders (holding scan.json) below the URL ``root``, sorted, as :func:`.batch.discover.iter_scans`
    finds them on disk: one listing per folder (:data:`LIST_THREADS` at a time, a level of the tree after
    another), a scan folder's subfolders not searched (nor listed: a scan.json nested there is not noted, to
    save a listing per scan).

    Raises:
        StorageError: the root cannot be listed (bucket not found, access denied, endpoint unreachable).
    """
    from concurrent.futures import ThreadPoolExecutor

    fs, path = filesystem(root, options)
    note = skipped.append if skipped is not None else (lambda item: None)
    scheme = _URL_RE.match(root)["scheme"]
    found: list[str] = []

    def ls(folder: str):
        try:
            with _mapped(f"{scheme}://{folder}"):
                return fs.ls(folder, detail=True)
        except StorageError as e:
            return e

    level, depth = [path], 0
    with ThreadPoolExecutor(max_workers=LIST_THREADS) as ex:
        while level and depth <= 64:
            below = []
            for folder, entries in zip(level, ex.map(ls, level)):
                url = f"{scheme}://{folder}"
                if isinstance(entries, StorageError):
                    if depth == 0:
                        raise entries
                    note((url, f"cannot list this folder: {entries.message}"))
                    continue
                names = {posixpath.basename(e["name"].rstrip("/")): e for e in entries}
                if "scan.json" in names and names["scan.json"].get("type") == "file":
                    found.append(url)
                    continue
                below += [f"{folder}/{n}" for n in sorted(names) if names[n].get("type") == "directory"]
            level, depth = below, depth + 1
    return sorted(found)


def write_json_to(location, obj, options: dict | None = None) -> None:
    """Write ``obj`` as indented JSON (as :func:`~.atomic.atomic_write_json`): atomically to a local path, as
    one whole object to a URL.

    Raises:
        StorageError: naming the URL (the bucket went away, access denied, endpoint unreachable).
    """
    from ringscan.pipeline.formats.atomic import atomic_write_json, json_safe

    if not is_url(location):
        atomic_write_json(local_path(location), obj)
        return
    data = (json.dumps(json_safe(obj), indent=2, allow_nan=False) + "\n").encode()
    fs, path = filesystem(location, options)
    with _mapped(location):
        fs.pipe_file(path, data)


def _remove_stale_stages(parent: Path) -> None:
    """Remove the staging folders of processes that no longer run (a worker killed mid-scan)."""
    try:
        entries = list(os.scandir(parent))
    except OSError:
        return
    for e in entries:
        m = _STAGE_RE.match(e.name)
        if m and not _process_alive(int(m["pid"])) and e.is_dir(follow_symlinks=False):
            shutil.rmtree(e.path, ignore_errors=True)


class Staged:
    """A scan and its output folder, local or staged from object storage (made by :func:`stage`)."""

    def __init__(self, scan: str, out: str | None, options: dict | None, tmp: Path | None):
        scan = os.fspath(scan)
        if is_url(scan) and scan.rstrip("/").endswith("/scan.json"):  # the scan.json named, as locally
            scan = scan.rstrip("/")[:-len("/scan.json")]
        self.scan_location, self.out_location, self.options = scan, out, options
        self.remote_scan = is_url(self.scan_location)
        self.remote_out = out is not None and is_url(out)
        self.scan_dir = tmp / "scan" if self.remote_scan else local_path(self.scan_location)
        """Where the scan is read: the scan folder, or its staged copy."""
        self.out_dir = (tmp / "out" if self.remote_out else local_path(out)) if out is not None else None
        """Where the results are written: the output folder, or its staged copy (:meth:`commit` uploads it)."""
        self.seconds = {"fetch": 0.0, "store": 0.0}
        """Seconds spent downloading (the scan's objects, the earlier results) and uploading (the results)."""
        self._objects: dict[str, dict] = {}  # the scan's objects: relative path -> info
        self._out_digests: dict[str, str] = {}  # the output objects downloaded: relative path -> MD5

    # -- the scan
    def _scan_url(self, rel: str) -> str:
        return join_location(self.scan_location, rel)

    def _download(self, fs, root: str, rels: list[str], dest: Path, base_url: str, *, limit: int, what: str,
                  infos: dict[str, dict], digests: dict | None = None) -> None:
        """Download objects ``rels`` (relative to ``root``) into ``dest``, each refused first when larger than
        ``limit``, given its object's modification time.

        Size: a private step of a fetch: the filesystem, the objects' root and names, the destination, and as
        keyword-only arguments the size limit and its message's word, the object infos its caller has already
        listed and the digests to fill.
        """
        for rel in rels:
            size = _size(infos[rel])
            if size > limit:
                raise FormatError(join_location(base_url, rel), f"{size} bytes: larger than the {limit} bytes a "
                                                                f"{what} may have")
        if not rels:
            return
        t = time.perf_counter()
        try:
            self._fetch(fs, root, rels, dest, base_url, limit=limit, what=what, infos=infos, digests=digests)
        finally:
            self.seconds["fetch"] += time.perf_counter() - t

    def _fetch(self, fs, root, rels, dest, base_url, *, limit, what, infos, digests) -> None:
        """Read objects ``rels`` (relative to ``root``) in one request and write each into ``dest``.

        Size: the arguments of _download, which it serves, passed on as they are.
        """
        keys = [f"{root}/{r}" for r in rels]
        with _mapped(join_location(base_url, rels[0])):
            got = fs.cat(keys, on_error="return") if len(keys) > 1 else {keys[0]: fs.cat_file(keys[0])}
        for rel, key in zip(rels, keys):
            data = got.get(key)
            url = join_location(base_url, rel)
            if isinstance(data, BaseException) or data is None:
                raise storage_error(url, data if data is not None else FileNotFoundError(key))
            if len(data) > limit:
                raise FormatError(url, f"larger than the {limit} bytes a {what} may have")
            target = dest / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
            t = _mtime_ns(infos[rel])
            os.utime(target, ns=(t, t))
            if digests is not None:
                digests[rel] = hashlib.md5(data).hexdigest()

    def _stage_scan(self) -> None:
        fs, root = filesystem(self.scan_location, self.options)
        self._fs, self._root = fs, root
        self._objects = _listing(fs, root, self.scan_location)
        if not self._objects:
            raise FormatError(self.scan_location, "scan folder not found")
        if "scan.json" not in self._objects:
            raise FormatError(self._scan_url("scan.json"), "file not found")
        self.scan_dir.mkdir(parents=True)
        self._download(fs, root, ["scan.json"], self.scan_dir, self.scan_location, limit=MAX_JSON_BYTES,
                       what="file", infos=self._objects)
        try:  # the other metadata it names; the loader checks everything (a bad scan.json is its error)
            d = json.loads((self.scan_dir / "scan.json").read_bytes())
        except ValueError:
            return
        wanted = []
        if isinstance(d, dict) and isinstance(d.get("rig"), str):
            wanted.append(d["rig"])
        views = d.get("views") if isinstance(d, dict) else None
        for vd in views if isinstance(views, list) else []:
            c2 = vd.get("camera2") if isinstance(vd, dict) else None
            for cam in (vd, c2):  # a two-camera view: camera 2's store too
                pk = cam.get("packed") if isinstance(cam, dict) else None
                if isinstance(pk, dict) and isinstance(pk.get("store"), str):
                    wanted.append(pk["store"] + "/zarr.json")
        rels = sorted({r for r in (_clean_rel(w) for w in wanted) if r in self._objects})
        self._download(fs, root, rels, self.scan_dir, self.scan_location, limit=MAX_JSON_BYTES, what="file",
                       infos=self._objects)

    def check_scan(self, scan) -> None:
        """Check that every frame a loaded scan lists is stored (for a local scan the loader did it).

        Raises:
            FormatError: naming the missing frame's URL, as the loader names a missing file.
        """
        if not self.remote_scan:
            return
        for i, view in enumerate(scan.views):
            for v, where in ((view, f"views[{i}]"), (view.camera2, f"views[{i}].camera2")):  # a two-camera view: both
                if v is None:
                    continue
                if v.packed is not None:
                    if not (self.scan_dir / v.packed / "zarr.json").is_file():
                        raise FormatError(self._scan_url(v.packed), f"frame store of {v.name} not found (listed "
                                                                    f"in scan.json {where}.packed.store)")
                    continue
                for k, rel in v.frames.items():
                    if rel not in self._objects:
                        raise FormatError(self._scan_url(rel), f"frame {k!r} of {v.name} not found (listed in "
                                                               f"scan.json {where}.frames)")

    @property
    def stat(self) -> Callable[[Path], list | None] | None:
        """A staged file -> its object's ``[size, mtime_ns]`` (for ``reconstruct.freshness``); None for a local
        scan (``os.stat``)."""
        if not self.remote_scan:
            return None

        def stat(path: Path):
            try:
                rel = Path(path).relative_to(self.scan_dir).as_posix()
            except ValueError:
                return None
            info = self._objects.get(rel)
            return None if info is None else [_size(info), _mtime_ns(info)]

        return stat

    def fetch_frames(self, scan, views=None) -> None:
        """Download the frames of ``views`` (names; default all) of a staged scan: image files, or a packed
        store's chunks (a chunk that is not stored is left to the reader, which names it)."""
        if not self.remote_scan:
            return
        from ringscan.pipeline.formats.scan import frame_files

        for v in scan.views:
            if views is not None and v.name not in views:
                continue
            paths = [p for cam in (v, v.camera2) if cam is not None for p in frame_files(scan, cam).values()]
            rels = sorted({p.relative_to(self.scan_dir).as_posix() for p in paths})
            rels = [r for r in rels if r in self._objects and not (self.scan_dir / r).exists()]
            self._download(self._fs, self._root, rels, self.scan_dir, self.scan_location, limit=MAX_OBJECT_BYTES,
                           what="frame", infos=self._objects)

    # -- the results
    def _stage_out(self) -> None:
        fs, root = filesystem(self.out_location, self.options)
        objects = {r: i for r, i in _listing(fs, root, self.out_location).items() if _is_result(r)}
        self.out_dir.mkdir(parents=True)
        self._download(fs, root, sorted(objects), self.out_dir, self.out_location, limit=MAX_OBJECT_BYTES,
                       what="result", infos=objects, digests=self._out_digests)

    def _renames(self) -> list[tuple[str, str]]:
        pairs = []
        if self.remote_scan:
            pairs.append((str(self.scan_dir), self.scan_location.rstrip("/")))
        if self.remote_out:
            pairs.append((str(self.out_dir), self.out_location.rstrip("/")))
        return pairs

    def rename(self, text: str) -> str:
        """``text`` with the staging folders replaced by the URLs they stand for."""
        for local, url in self._renames():
            text = text.replace(local, url)
        return text

    def _json_for_upload(self, data: bytes) -> bytes:
        try:
            obj = json.loads(data)
        except ValueError:
            return data

        def fix(o):
            if isinstance(o, str):
                return self.rename(o)
            if isinstance(o, list):
                return [fix(v) for v in o]
            if isinstance(o, dict):
                return {k: fix(v) for k, v in o.items()}
            return o

        return (json.dumps(fix(obj), indent=2, allow_nan=False) + "\n").encode()

    def commit(self) -> int:
        """Store the results: upload every result file of a staged output folder that is new or changed (since
        it was staged or last committed), each as one whole object, the reports after the files they list and
        ``report.json`` last; in a local output folder, name the scan's URL instead of its staging folder in
        the reports. Returns the objects uploaded; ``seconds["store"]`` counts the time.

        Raises:
            StorageError: naming the object's URL (the bucket went away, access denied, ...).
        """
        if self.out_dir is None or not self._renames() or not self.out_dir.is_dir():
            return 0
        # the files a reconstruction and a fusion write, nothing else of the folder (a local one may hold more)
        found = list(self.out_dir.iterdir()) + [p for d in RESULT_FOLDERS if (self.out_dir / d).is_dir()
                                                 for p in (self.out_dir / d).iterdir()]
        files = sorted(p for p in found if p.is_file() and _is_result(p.relative_to(self.out_dir).as_posix()))
        files.sort(key=lambda p: (p.suffix == ".json", p.parent == self.out_dir and p.name == "report.json"))
        if not self.remote_out:  # a staged scan, local results: the reports name the scan's URL
            for p in files:
                if p.suffix == ".json" and str(self.scan_dir) in (text := p.read_text()):
                    atomic_write_bytes(p, self._json_for_upload(text.encode()))
            return 0
        fs, root = filesystem(self.out_location, self.options)
        sent = 0
        t = time.perf_counter()
        try:
            for p in files:
                sent += self._store(fs, root, p)
        finally:
            self.seconds["store"] += time.perf_counter() - t
        if sent:
            log.info("%s: %d object(s) stored", self.out_location, sent)
        return sent

    def _store(self, fs, root: str, p: Path) -> int:
        """Upload one result file unless the store holds these bytes already; returns 1 if it was sent."""
        rel = p.relative_to(self.out_dir).as_posix()
        data = p.read_bytes()
        if p.suffix == ".json":
            data = self._json_for_upload(data)
        digest = hashlib.md5(data).hexdigest()
        if self._out_digests.get(rel) == digest:
            return 0
        with _mapped(join_location(self.out_location, rel)):
            fs.pipe_file(f"{root}/{rel}", data)
        self._out_digests[rel] = digest
        return 1


RESULT_FOLDERS = ("fused", "mesh")
"""Subfolders of a scan's results (``--fuse``, ``--mesh``); with the PLYs and JSON files beside them, the only
objects of an output folder that are staged (an output URL given as a whole bucket stages no more)."""


def _is_result(rel: str) -> bool:
    parts = rel.split("/")
    if any(p.startswith(".") for p in parts) or not rel.endswith((".ply", ".json")):
        return False
    return len(parts) == 1 or (len(parts) == 2 and parts[0] in RESULT_FOLDERS)


def _clean_rel(rel: str) -> str | None:
    p = posixpath.normpath(rel.replace("\\", "/"))
    return None if p.startswith(("/", "../")) or p == ".." else p


@contextlib.contextmanager
def stage(scan, out=None, *, options: dict | None = None, outputs: bool = True) -> Iterator[Staged]:
    """A scan and its output folder as local folders: themselves when local, else staged copies in a private
    temporary folder (removed at the end; one left by a killed process is removed by the next stage).

    Args:
        scan: the scan folder: a path or a URL.
        out: the output folder: a path or a URL (None: none).
        options: fsspec storage options of the URLs.
        outputs: download the output folder's objects (False: start from an empty one).

    Yields:
        :class:`Staged`: ``scan_dir`` and ``out_dir`` to read and write; ``fetch_frames`` before reading frames,
        ``commit`` to store the results. A :class:`FormatError` raised inside names URLs, not staged files.
    """
    if not is_url(scan) and not (out is not None and is_url(out)):
        yield Staged(scan, None if out is None else os.fspath(out), options, None)
        return
    parent = Path(tempfile.gettempdir())
    _remove_stale_stages(parent)
    while True:
        tmp = parent.resolve() / f"ringscan-stage-{os.getpid()}-{secrets.token_hex(4)}"
        try:
            tmp.mkdir(mode=0o700)
            break
        except FileExistsError:
            continue
    st = Staged(scan, None if out is None else os.fspath(out), options, tmp)
    try:
        if st.remote_scan:
            st._stage_scan()
        if st.remote_out:
            if outputs:
                st._stage_out()
            else:
                st.out_dir.mkdir(parents=True)
        yield st
    except StorageError:
        raise
    except FormatError as e:
        raise type(e)(st.rename(e.path) if e.path else None, st.rename(e.message)) from None
    except (RingscanError, ValueError) as e:  # e.g. "unknown view(s) ... in <scan.json>": the URL, not the stage
        if type(e) in (RingscanError, ValueError) and str(tmp) in str(e):
            raise type(e)(st.rename(str(e))) from None
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
