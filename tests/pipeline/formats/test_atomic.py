"""Atomic writes: the mode a new file gets, the mode an overwritten file keeps,
leftover temporary files, output paths that cannot be written, strict JSON."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.formats.atomic import (
    atomic_path,
    atomic_write_bytes,
    atomic_write_json,
    check_no_overwrite,
    check_output_file,
    check_output_folder,
    read_json,
    remove_stale_temporaries,
)
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.meshes import write_mesh
from ringscan.pipeline.formats.ply import write_ply


@pytest.fixture(params=[0o022, 0o002], ids=["umask022", "umask002"])
def umask(request):
    old = os.umask(request.param)
    yield request.param
    os.umask(old)


def _mode(p) -> int:
    return stat.S_IMODE(os.stat(p).st_mode)


def _write_every_kind(folder):
    """One file of every kind ringscan writes, through its writers."""
    atomic_write_bytes(folder / "a.txt", b"x")
    atomic_write_json(folder / "a.json", {"a": 1})
    write_image(folder / "a.png", np.zeros((4, 5), np.uint8))
    write_ply(folder / "a.ply", {"x": np.zeros(3, np.float32)})
    write_mesh(folder / "m.stl", o3d.geometry.TriangleMesh.create_tetrahedron())
    return ["a.txt", "a.json", "a.png", "a.ply", "m.stl"]


def test_new_files_get_the_mode_the_umask_gives(tmp_path, umask):
    for name in _write_every_kind(tmp_path):
        assert _mode(tmp_path / name) == 0o666 & ~umask, name


def test_an_overwritten_file_keeps_its_mode(tmp_path, umask):
    names = _write_every_kind(tmp_path)
    for name in names:
        os.chmod(tmp_path / name, 0o640)
    _write_every_kind(tmp_path)
    for name in names:
        assert _mode(tmp_path / name) == 0o640, name
    assert not list(tmp_path.glob(".*"))  # no temporary file left


def _killed_writer(folder, name: str) -> None:
    """A process that dies (SIGKILL) in the middle of an atomic write of folder/name."""
    code = ("import os, signal, sys; from pathlib import Path;"
            "from ringscan.pipeline.formats.atomic import atomic_path\n"
            f"with atomic_path(Path({str(folder)!r}) / {name!r}) as tmp:\n"
            "    tmp.write_bytes(b'half a file')\n"
            "    os.kill(os.getpid(), signal.SIGKILL)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True)
    assert res.returncode == -9, res.stderr


def test_a_killed_writers_temporary_file_is_removed(tmp_path):
    _killed_writer(tmp_path, "report.json")
    left = list(tmp_path.glob(".report.json.*.tmp.json"))
    assert len(left) == 1 and not (tmp_path / "report.json").exists()
    # a live writer's temporary file (this process) and other dot files are kept
    with atomic_path(tmp_path / "live.json") as live:
        live.write_bytes(b"{}")
        (tmp_path / ".hidden").write_text("mine")
        removed = remove_stale_temporaries(tmp_path)
        assert removed == left and live.exists()
    assert not left[0].exists() and (tmp_path / ".hidden").is_file() and (tmp_path / "live.json").is_file()
    # a temporary file of the earlier naming (tempfile.mkstemp, no process id): removed when old
    old = tmp_path / ".view_000.ab_cd12x.tmp.ply"
    old.write_bytes(b"")
    assert remove_stale_temporaries(tmp_path) == []
    os.utime(old, (time.time() - 7200, time.time() - 7200))
    assert remove_stale_temporaries(tmp_path) == [old]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="zombies are told apart through /proc (Linux)")
def test_a_temporary_file_of_a_killed_but_unreaped_writer_is_removed(tmp_path):
    """A batch worker killed with its pool is a zombie until the pool reaps it; its pid
    still answers kill(pid, 0), yet it will write nothing more: its file is stale."""
    child = subprocess.Popen([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"])
    try:
        deadline = time.time() + 30
        while Path(f"/proc/{child.pid}/stat").read_bytes().rsplit(b")", 1)[1].split()[0] != b"Z":
            assert time.time() < deadline, "the child did not die"
            time.sleep(0.01)
        tmp = tmp_path / f".report.json.{child.pid}-abcd1234.tmp.json"
        tmp.write_bytes(b"{")
        assert remove_stale_temporaries(tmp_path) == [tmp]
    finally:
        child.wait()


def test_output_folder_checks(tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    assert check_output_folder(tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"
    with pytest.raises(FormatError, match="afile: cannot be the output folder: it exists and is a file"):
        check_output_folder(f)
    with pytest.raises(FormatError, match="sub: cannot be the output folder: it lies under .*afile, which is a file"):
        check_output_folder(f / "sub")
    with pytest.raises(FormatError, match="/dev/null: .*is a device"):
        check_output_folder("/dev/null")
    (tmp_path / "broken").symlink_to(tmp_path / "nowhere")
    with pytest.raises(FormatError, match="broken symbolic link"):
        check_output_folder(tmp_path / "broken")


def test_output_file_checks(tmp_path):
    (tmp_path / "afile").write_text("x")
    assert check_output_file(tmp_path / "afile") == tmp_path / "afile"  # replaced: fine
    with pytest.raises(FormatError, match="it is a folder"):
        check_output_file(tmp_path)
    with pytest.raises(FormatError, match="/dev/null: .*a device"):
        check_output_file("/dev/null", extensions=(".png",))
    with pytest.raises(FormatError, match="lies under"):
        check_output_file(tmp_path / "afile" / "x.png")
    with pytest.raises(FormatError, match=r"x.gif: .*extension must be .png, not '.gif'"):
        check_output_file(tmp_path / "x.gif", extensions=(".png",))
    # the writers themselves refuse a folder where the file goes, and name it
    (tmp_path / "report.json").mkdir()
    with pytest.raises(FormatError, match="report.json: is a folder, where ringscan writes a file"):
        atomic_write_json(tmp_path / "report.json", {})
    with pytest.raises(FormatError, match="lies under"):
        atomic_write_bytes(tmp_path / "afile" / "x.txt", b"")


def test_no_overwrite_of_inputs_through_links(tmp_path):
    (tmp_path / "in.json").write_text("{}")
    (tmp_path / "link").symlink_to(tmp_path, target_is_directory=True)
    check_no_overwrite([tmp_path / "out.json"], [tmp_path / "in.json"])
    with pytest.raises(FormatError, match="would overwrite the input"):
        check_no_overwrite([tmp_path / "link" / "in.json"], [tmp_path / "in.json"])


def test_json_written_is_strict(tmp_path):
    atomic_write_json(tmp_path / "r.json", {"a": float("nan"), "b": [float("inf"), np.float32("nan"), 1.5],
                                            "c": np.arange(2), "d": np.int64(3)})

    def no_constants(name):
        raise AssertionError(f"{name} is not JSON")

    d = json.loads((tmp_path / "r.json").read_text(), parse_constant=no_constants)
    assert d == {"a": None, "b": [None, None, 1.5], "c": [0, 1], "d": 3}


def test_read_json_names_the_file(tmp_path):
    p = tmp_path / "scan.json"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe")
    with pytest.raises(FormatError, match=r"scan.json: not a text file: byte 0x89 at offset 0 is not UTF-8"):
        read_json(p)
    with pytest.raises(FormatError, match=r"'.*sc\\x00an.json': the path contains a NUL"):
        read_json(tmp_path / "sc\0an.json")
    with pytest.raises(FormatError, match="is a folder"):
        read_json(tmp_path)


def test_lock_folder_one_holder_at_a_time_and_a_dead_holder_taken_over(tmp_path):
    import os
    import subprocess
    import sys

    from ringscan.pipeline.formats.atomic import LOCK_NAME, FolderInUse, lock_folder

    lock = tmp_path / LOCK_NAME
    with lock_folder(tmp_path, what="batch") as p:
        assert p == lock and lock.read_text() == f"{os.getpid()} batch\n"
        with pytest.raises(FolderInUse, match=rf"in use by another ringscan run \(batch, process {os.getpid()}\)"):
            with lock_folder(tmp_path, what="import"):
                pass
    assert not lock.exists()
    # a holder killed with SIGKILL leaves its file; the kernel dropped its lock: taken over
    proc = subprocess.Popen([sys.executable, "-c", "import os, signal\n"
                             "from ringscan.pipeline.formats.atomic import lock_folder\n"
                             f"with lock_folder({str(tmp_path)!r}, what='reconstruct'):\n"
                             "    os.kill(os.getpid(), signal.SIGKILL)"])
    assert proc.wait() == -9 and lock.read_text().split() == [str(proc.pid), "reconstruct"]
    with lock_folder(tmp_path, what="batch"):
        assert lock.read_text() == f"{os.getpid()} batch\n"
    assert not lock.exists()


def test_a_lock_file_that_is_a_link_a_fifo_or_a_hard_link_is_refused_and_left_alone(tmp_path):
    """Before: a symbolic link's target (another file) was truncated and written; a FIFO gave
    `Invalid argument` without a path and was removed."""
    import os

    from ringscan.pipeline.formats.atomic import LOCK_NAME, lock_folder

    lock = tmp_path / LOCK_NAME
    other = tmp_path / "precious.txt"
    other.write_text("keep me\n")
    cases = [("link", lambda: lock.symlink_to(other), f"is a symbolic link (to {other}), not a plain file"),
             ("fifo", lambda: os.mkfifo(lock), "is a pipe (FIFO), not a plain file"),
             ("hard link", lambda: os.link(other, lock), "has 2 hard links: another file shares its contents")]
    for name, make, why in cases:
        make()
        with pytest.raises(FormatError) as e:
            with lock_folder(tmp_path, what="batch"):
                pytest.fail(f"{name}: the lock was taken")
        assert str(e.value) == (f"{lock}: {why}: it is ringscan's own lock file, a plain file: remove it (no "
                                "ringscan run uses it then)"), name
        assert os.path.lexists(lock) and other.read_text() == "keep me\n", name
        lock.unlink()


def test_a_folder_another_writer_makes_meanwhile_is_a_folder(tmp_path, monkeypatch):
    """The output checks look at a path twice (is it a folder? does it exist?); a folder another writer
    (the import's threads, each writing one camera's files) makes between the two is a folder, not an
    error ("... which is a folder, not a folder" failed a fresh-clone CI run once)."""
    import pathlib

    from ringscan.pipeline.formats.atomic import check_output_file, check_output_folder

    target = tmp_path / "out" / "capture_0"
    real_is_dir = pathlib.Path.is_dir
    first = {}

    def racing_is_dir(self, *a, **k):
        if self in (target, target.parent) and self not in first:
            first[self] = True
            self.mkdir(parents=True, exist_ok=True)  # the other writer, just now
            return False
        return real_is_dir(self, *a, **k)

    monkeypatch.setattr(pathlib.Path, "is_dir", racing_is_dir)
    assert check_output_folder(target) == target
    assert check_output_file(target / "proj_u.png") == target / "proj_u.png"
    assert len(first) >= 1  # the race was taken
