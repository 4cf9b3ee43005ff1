"""Atomic writes, JSON files, and checks of output paths.

Writes go to a temporary file in the same folder and are moved into place with
``os.replace``, so a crash never leaves a half-written file behind: a reader sees
the old file or the new one. The temporary file is created with mode 0666 less
the process's umask (the mode any new file gets, 0644 under the usual umask 022);
a file that is overwritten keeps the mode it had.

A writer that is killed (SIGKILL, power loss) leaves its temporary file
(``.<name>.<pid>-<random>.tmp<ext>``) behind; :func:`remove_stale_temporaries`
removes those of processes that no longer run (``ringscan reconstruct``,
``batch`` and ``fuse`` call it on their output folders).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import secrets
import stat
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.limits import MAX_JSON_BYTES, mode_kind, read_bounded_bytes

log = logging.getLogger(__name__)

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_json", "read_json", "remove_stale_temporaries", "FolderInUse",
           "check_output_folder", "check_output_file", "check_no_overwrite", "json_safe", "lock_folder", "LOCK_NAME"]

LOCK_NAME = ".ringscan.lock"
"""The lock file of an output folder in use (:func:`lock_folder`): it holds the owner's process id."""

_TMP_RE = re.compile(r"^\.(?P<target>.+)\.(?P<pid>\d+)-[0-9a-f]{8}\.tmp(\.[^./]*)?$")
# Temporary files of ringscan before the writer's process id was part of the name
# (tempfile.mkstemp: 8 characters of [a-z0-9_]); removed once they are an hour old.
_OLD_TMP_RE = re.compile(r"^\.(?P<target>.+)\.[a-z0-9_]{8}\.tmp(\.[^./]*)?$")
_OLD_TMP_AGE_S = 3600.0


def _kind(p: Path) -> str:
    """What an existing non-folder path is, in words."""
    try:
        m = p.lstat().st_mode
    except OSError:
        return "unreadable"
    if stat.S_ISLNK(m) and not p.exists():
        return "a broken symbolic link"
    try:
        m = p.stat().st_mode
    except OSError:
        return "unreadable"
    return "a file" if stat.S_ISREG(m) else mode_kind(m)


def _check_ancestors(p: Path, what: str) -> None:
    for a in p.parents:
        if a.is_dir():
            return
        # a.is_dir() again: another writer (the import's threads) may have made the folder in between
        if (a.exists() or a.is_symlink()) and not a.is_dir():
            raise FormatError(p, f"cannot be the {what}: it lies under {a}, which is {_kind(a)}, not a folder")


def check_output_folder(path: str | os.PathLike, *, what: str = "output folder") -> Path:
    """Check that ``path`` can be an output folder: a folder, or a path that can
    be created as one (nothing on the way is a file). Returns it as a Path.

    Raises:
        FormatError: naming the path: it is a file, a device (``/dev/null``), a
            broken link, or lies under a file.
    """
    p = Path(path)
    if "\0" in str(p):
        raise FormatError(p, f"cannot be the {what}: the path contains a NUL character")
    if p.is_dir():
        return p
    if (p.exists() or p.is_symlink()) and not p.is_dir():  # (made by another writer in between: a folder)
        raise FormatError(p, f"cannot be the {what}: it exists and is {_kind(p)}, not a folder")
    _check_ancestors(p, what)
    return p


def check_output_file(path: str | os.PathLike, *, extensions: Iterable[str] | None = None,
                      what: str = "output file") -> Path:
    """Check that ``path`` can be written as a regular file (new, or a file that is
    replaced), with one of ``extensions`` (lower case, with the dot) when given.

    Raises:
        FormatError: naming the path: it is a folder, a device (``/dev/null``), a
            pipe, lies under a file, or has another extension.
    """
    p = Path(path)
    if "\0" in str(p):
        raise FormatError(p, f"cannot be the {what}: the path contains a NUL character")
    if p.is_dir():
        raise FormatError(p, f"cannot be the {what}: it is a folder")
    if p.exists() or p.is_symlink():
        if _kind(p) != "a file":
            raise FormatError(p, f"cannot be the {what}: it is {_kind(p)}; ringscan writes regular files only")
    else:
        _check_ancestors(p, what)
    if extensions is not None:
        exts = tuple(extensions)
        if p.suffix.lower() not in exts:
            raise FormatError(p, f"cannot be the {what}: the extension must be {' or '.join(exts)}, "
                                 f"not {p.suffix or '(none)'!r}")
    return p


def check_no_overwrite(outputs: Iterable[str | os.PathLike], inputs: Iterable[str | os.PathLike]) -> None:
    """Refuse outputs that are (through links too) one of the inputs.

    Raises:
        FormatError: naming the output and the input it would overwrite.
    """
    ins = {}
    for q in inputs:
        ins.setdefault(os.path.realpath(q), Path(q))
    for o in outputs:
        q = ins.get(os.path.realpath(o))
        if q is None and Path(o).exists():
            q = next((i for i in ins.values() if i.exists() and os.path.samefile(i, o)), None)
        if q is not None:
            raise FormatError(o, f"writing it would overwrite the input {q}; choose another output")


def _new_temporary(path: Path, suffix: str) -> Path:
    """Create an empty temporary file next to ``path`` (mode 0666 less the umask)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp{suffix}"
        try:
            fd = os.open(tmp, flags, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"{path.parent}: could not create a temporary file for {path.name}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None):
    """Yield a temporary path next to ``path``; move it into place on success.

    The temporary file keeps the same extension (OpenCV and Open3D pick the
    format from it). On an exception the temporary file is removed and ``path``
    is left as it was. The new file gets the mode of the file it replaces, or
    0666 less the umask.

    Raises:
        FormatError: ``path`` is a folder or not a regular file, or its folder
            cannot be made (it lies under a file).
    """
    path = Path(path)
    if path.is_dir():
        raise FormatError(path, "is a folder, where ringscan writes a file: move it away or choose another output")
    if (path.exists() or path.is_symlink()) and _kind(path) != "a file":
        raise FormatError(path, f"is {_kind(path)}, where ringscan writes a file: choose another output")
    if "\0" in str(path):
        raise FormatError(path, "cannot be written: the path contains a NUL character")
    _check_ancestors(path, "file to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    tmp = _new_temporary(path, suffix)
    try:
        yield tmp
        try:
            mode = stat.S_IMODE(os.stat(path).st_mode)
        except FileNotFoundError:
            mode = None
        if mode is not None:
            os.chmod(tmp, mode)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files that killed writers left in ``folder`` (not below it).

    A temporary file of :func:`atomic_path` carries its writer's process id; it is
    removed when that process no longer runs (a live writer, this process
    included, keeps its file). Temporary files of older ringscan versions (no
    process id) are removed once they are an hour old. Returns the removed paths.
    """
    folder = Path(folder)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return removed
    now = time.time()
    for e in entries:
        if not e.name.startswith(".") or ".tmp" not in e.name or not e.is_file(follow_symlinks=False):
            continue
        m = _TMP_RE.match(e.name)
        if m is not None:
            stale = not _process_alive(int(m["pid"]))
        else:
            stale = _OLD_TMP_RE.match(e.name) is not None and now - e.stat().st_mtime > _OLD_TMP_AGE_S
        if stale:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(e.path)
                removed.append(Path(e.path))
    if removed:
        log.info("%s: removed %d temporary file(s) left by an interrupted run", folder, len(removed))
    return removed


def _process_alive(pid: int) -> bool:
    """Whether process ``pid`` still runs. A zombie (exited, not yet reaped by its
    parent: a batch worker just killed, say) does not: it will write nothing more."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            state = f.read().rsplit(b")", 1)[1].split()[0]
    except (OSError, IndexError):  # no /proc (not Linux): it exists, so it runs
        return True
    return state not in (b"Z", b"X")


class FolderInUse(FormatError):
    """An output folder is locked by another ringscan run."""


@contextlib.contextmanager
def lock_folder(folder: str | os.PathLike, *, what: str = "ringscan"):
    """Hold ``folder`` (an output folder, which must exist) for this run: one run at a time.

    The lock is ``folder/.ringscan.lock``, locked with ``flock`` and holding the owner's
    process id and command; the kernel drops the lock when its process ends however it
    ends, so a lock left by a killed run is taken over by the next. The file is removed
    when the run ends.

    Raises:
        FolderInUse: (a FormatError) another live process holds the folder; the message
            names the folder and that process.
    """
    import fcntl

    path = Path(folder) / LOCK_NAME
    while True:
        fd = _open_lock_file(path)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                owner = os.pread(fd, 200, 0).decode("utf-8", "replace").split()
            finally:
                os.close(fd)
            who = f"{owner[1]}, process {owner[0]}" if len(owner) >= 2 else "another process"
            raise FolderInUse(folder, f"in use by another ringscan run ({who}); wait for it to end or choose "
                                      f"another output folder (lock file {LOCK_NAME})") from None
        except OSError as e:  # a file system without locks (ENOLCK, EOPNOTSUPP): run unguarded, say so
            os.close(fd)
            log.warning("%s: cannot lock this folder (%s): a second run into it would not be refused", folder,
                        e.strerror)
            with contextlib.suppress(OSError):
                if path.stat().st_size == 0:  # ours, just created
                    path.unlink()
            yield None
            return
        # The previous owner may have removed the file between our open and our lock: lock the file that is there.
        try:
            same = os.path.samestat(os.fstat(fd), os.lstat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {what}\n".encode(), 0)
        yield path
    finally:
        with contextlib.suppress(FileNotFoundError):
            if os.path.samestat(os.fstat(fd), os.lstat(path)):  # ours still: not a file put there since
                os.unlink(path)
        os.close(fd)


def _open_lock_file(path: Path) -> int:
    """Open (create) a lock file for reading and writing, refusing anything but a plain file of its own:
    a symbolic link (the run would write into the file it points to), a FIFO or a device (the open would
    block, or the write go elsewhere), a file with another hard link (truncating it would empty that file).

    Raises:
        FormatError: naming the lock file and what it is; nothing is written to it or removed.
    """
    flags = (os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)
             | getattr(os, "O_NONBLOCK", 0))
    fix = "it is ringscan's own lock file, a plain file: remove it (no ringscan run uses it then)"
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as e:
        if os.path.islink(path):
            raise FormatError(path, f"is a symbolic link (to {os.readlink(path)}), not a plain file: {fix}") from None
        raise FormatError(path, f"cannot open the lock file: {e.strerror}") from None
    st = os.fstat(fd)
    why = (f"is {mode_kind(st.st_mode)}, not a plain file" if not stat.S_ISREG(st.st_mode)
           else f"has {st.st_nlink} hard links: another file shares its contents" if st.st_nlink != 1 else None)
    if why:
        os.close(fd)
        raise FormatError(path, f"{why}: {fix}")
    return fd


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_json(path: str | os.PathLike, obj) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically.

    The file is strict JSON: NaN and infinite numbers (which JSON has no token for)
    are written as ``null``.
    """
    text = json.dumps(json_safe(obj), indent=2, allow_nan=False)
    atomic_write_bytes(path, (text + "\n").encode())


def json_safe(o):
    """``o`` with NumPy values turned into Python ones and NaN/inf into None (JSON null)."""
    if isinstance(o, dict):
        return {str(k) if isinstance(k, Path) else k: json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_safe(v) for v in o]
    if isinstance(o, np.ndarray):
        return json_safe(o.tolist())
    if isinstance(o, (np.bool_, np.integer, np.floating)):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, Path):
        return str(o)
    if o is None or isinstance(o, (str, int, float, bool)):
        return o
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_json(path: str | os.PathLike, *, max_bytes: int = MAX_JSON_BYTES) -> dict:
    """Read a JSON object, raising :class:`FormatError` naming the file on failure.

    Only a regular file of at most ``max_bytes`` is read (a FIFO or ``/dev/zero`` is
    refused before reading: :func:`~.limits.read_bounded_bytes`).
    """
    path = Path(path)
    if path.is_dir():
        raise FormatError(path, "is a folder, not a JSON file")
    raw = read_bounded_bytes(path, max_bytes, what="file")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise FormatError(path, f"not a text file: byte 0x{raw[e.start]:02x} at offset {e.start} is not UTF-8 "
                                "(expected JSON)") from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise FormatError(path, f"not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except RecursionError:
        raise FormatError(path, "not valid JSON (nested too deeply)") from None
    except ValueError as e:  # e.g. an integer of more than 4300 digits
        raise FormatError(path, f"not valid JSON ({str(e).split(';')[0]})") from None
    if not isinstance(obj, dict):
        raise FormatError(path, "expected a JSON object at the top level")
    return obj
