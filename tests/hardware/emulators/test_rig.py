"""The emulated rig's temporary folder: removed on close, and a killed rig's removed by the next rig."""

import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from ringscan.hardware.emulators.rig import FOLDER_PREFIX, EmulatedRig, remove_stale_folders
from ringscan.pipeline.formats.atomic import LOCK_NAME, lock_folder
from tests.support.hardware_rig import small_patterns

REPO = Path(__file__).resolve().parents[3]

# A process that starts a rig in its own temporary folder, says where, and waits to be killed.
_RIG = """
import sys
from ringscan.hardware.emulators.rig import EmulatedRig
from tests.support.hardware_rig import small_patterns, small_rig

emu = EmulatedRig(small_rig(), small_patterns(), "terrain", device="cpu")
print(emu.folder, flush=True)
sys.stdin.read()
"""


def _emu_folders(parent):
    return sorted(p.name for p in Path(parent).glob(FOLDER_PREFIX + "*"))


def test_a_killed_rigs_folder_is_removed_by_the_next_rig(tmp_path, monkeypatch, rig, virtual_rig):
    temp = tmp_path / "tmp"
    temp.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", _RIG], cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True, env=dict(os.environ, TMPDIR=str(temp), PYTHONPATH=str(REPO)))
    try:
        killed = Path(proc.stdout.readline().strip())
        assert killed.parent == temp and (killed / "turntable").is_symlink() and (killed / LOCK_NAME).is_file()
        proc.send_signal(signal.SIGKILL)  # no finally, no handler: the folder stays
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stdin.close()
    assert _emu_folders(temp) == [killed.name]
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    with EmulatedRig(rig, small_patterns(), virtual_rig=virtual_rig) as emu:
        assert _emu_folders(temp) == [emu.folder.name]  # the killed one's is gone, its own is there
        assert sorted(p.name for p in emu.folder.iterdir()) == [LOCK_NAME, "projector", "turntable"]
    assert _emu_folders(temp) == []  # closed: its own is gone too


def test_only_folders_of_dead_rigs_are_removed(tmp_path):
    def folder(name, lock_text=None):
        d = tmp_path / f"{FOLDER_PREFIX}{name}"
        d.mkdir()
        os.symlink("/dev/null", d / "turntable")
        (d / "rig.json").write_text("{}")
        if lock_text is not None:
            (d / LOCK_NAME).write_text(lock_text)
        return d

    dead = folder("dead", "4242 emulate\n")  # what a killed rig leaves: a lock file nobody holds
    starting = folder("starting", "")  # created, not yet locked by its owner
    old = folder("old")  # no lock file: not known to be dead
    live = folder("live")
    other = tmp_path / "other-folder"
    other.mkdir()
    (other / LOCK_NAME).write_text("4242 emulate\n")
    with lock_folder(live, what="emulate"):  # a running rig's (flock: another open conflicts, in one process too)
        assert remove_stale_folders(tmp_path) == [dead]
        assert not dead.exists() and starting.is_dir() and old.is_dir() and other.is_dir()
        assert sorted(p.name for p in live.iterdir()) == [LOCK_NAME, "rig.json", "turntable"]
