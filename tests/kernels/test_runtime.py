"""kernels.runtime: device names checked at the edge; kernels.process: the host allocator's policy."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ringscan.kernels.process import retain_freed_memory
from ringscan.kernels.runtime import resolve_device

PROBE = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from ringscan.kernels.process import retain_freed_memory
    if sys.argv[1] == "retain" and not retain_freed_memory():
        sys.exit(3)
    if sys.argv[1] == "off" and retain_freed_memory():  # RINGSCAN_KEEP_FREED_MB=0
        sys.exit(4)

    def view():  # a view's worth of per-pixel arrays, every page written, then all freed
        arrs = [np.empty(5 << 20, np.uint8) for _ in range(12)]
        for a in arrs:
            a[::4096] = 1
        del arrs

    view(); view()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        view()
    print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 5)
""")


def _faults_per_view(mode: str, env: dict | None = None) -> float:
    import os

    r = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=120,
                       env={**os.environ, **(env or {})})
    if r.returncode == 3:
        pytest.skip("this C library has no mallopt (not glibc): retain_freed_memory changes nothing")
    assert r.returncode == 0, r.stderr
    return float(r.stdout.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator policy: Linux only")
def test_retained_memory_is_not_faulted_in_again():
    """60 MB of arrays allocated and freed per view: glibc's default gives the memory back
    and the next view faults its pages in again; with retain_freed_memory the pages stay."""
    default = _faults_per_view("default")
    kept = _faults_per_view("retain")
    assert default > 1000  # what the policy is for (about one fault per 4 KiB page given back)
    assert kept < 0.02 * default
    # RINGSCAN_KEEP_FREED_MB=0 turns it off: the default behaviour again
    off = _faults_per_view("off", {"RINGSCAN_KEEP_FREED_MB": "0"})
    assert off > 0.5 * default


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator policy: Linux only")
def test_the_policy_keeps_numpys_arrays_on_base_pages():
    """With the policy on, NumPy no longer advises huge pages for its arrays (its setter returns the setting it
    replaces); off (RINGSCAN_KEEP_FREED_MB=0), NumPy's own default stands."""
    import os

    probe = ("import sys\nfrom numpy._core.multiarray import _set_madvise_hugepage as s\n"
             "from ringscan.kernels.process import retain_freed_memory\n"
             "default = s(True); s(default)\n"
             "on = retain_freed_memory()\n"
             "print(default, on, s(True))\n")
    outs = []
    for env in ({}, {"RINGSCAN_KEEP_FREED_MB": "0"}):
        r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
                           env={**os.environ, **env})
        assert r.returncode == 0, r.stderr
        outs.append(r.stdout.split())
    (default, on, after), (default_off, on_off, after_off) = outs
    if on == "False":
        pytest.skip("this C library has no mallopt (not glibc): retain_freed_memory changes nothing")
    if default == "False":
        pytest.skip("NumPy advises no huge pages on this kernel: nothing to turn off")
    assert after == "False"  # advice off while the policy holds
    assert on_off == "False" and after_off == default_off  # policy off: NumPy's default as it was


BLAS_PROBE = """
import json, subprocess, sys
import numpy, scipy.linalg
from threadpoolctl import threadpool_info
from ringscan.kernels.process import one_blas_thread
def blas():
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
before = blas()
done = one_blas_thread()
child = subprocess.run([sys.executable, "-c", "import os; print(os.environ.get('OPENBLAS_NUM_THREADS'))"],
                       capture_output=True, text=True).stdout.strip()
print(json.dumps({"done": done, "before": before, "after": blas(), "child": child}))
"""


def test_blas_runs_on_one_thread_in_ringscans_processes_unless_the_user_says():
    """After one_blas_thread NumPy's and SciPy's OpenBLAS (both loaded before it) run one thread each, and
    a child process (a batch worker) starts with OPENBLAS_NUM_THREADS=1; with the user's OMP_NUM_THREADS
    set, nothing changes. (Where BLAS already runs one thread, a one-core machine, there is nothing to
    limit: skipped.)"""
    import json
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                          "MKL_NUM_THREADS")}

    def probe(extra):
        r = subprocess.run([sys.executable, "-c", BLAS_PROBE], capture_output=True, text=True, timeout=120,
                           env={**env, **extra})
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)

    mine = probe({})
    assert mine["before"]  # NumPy's (and SciPy's own, with the wheels)
    if max(mine["before"]) <= 1:
        pytest.skip("BLAS already runs one thread here (one core)")
    assert mine["done"] and mine["after"] == [1] * len(mine["before"]) and mine["child"] == "1"
    theirs = probe({"OMP_NUM_THREADS": "2"})
    assert not theirs["done"] and theirs["after"] == theirs["before"] and theirs["child"] == "None"


def test_retain_freed_memory_is_safe_to_call_again():
    first = retain_freed_memory()
    assert retain_freed_memory() == first


FREEZE_PROBE = """
import gc, json
import numpy
from ringscan.kernels.process import freeze_imported_objects
before = gc.get_freeze_count()
freeze_imported_objects()
first = gc.get_freeze_count()
junk = [[object()] for _ in range(1000)]
freeze_imported_objects()
print(json.dumps({"before": before, "first": first, "again": gc.get_freeze_count()}))
"""


def test_the_imports_objects_are_frozen_once_a_process():
    """freeze_imported_objects moves what the imports made (thousands of objects: NumPy's, ringscan's) out of the
    collector's passes, once: a second call (a test session running the command again) freezes nothing new."""
    import json

    r = subprocess.run([sys.executable, "-c", FREEZE_PROBE], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["before"] == 0 and got["first"] > 10000 and got["again"] == got["first"]


def test_resolve_device_names():
    assert resolve_device("cpu") == "cpu"
    with pytest.raises(ValueError, match="unknown"):
        resolve_device("tpu:0")


EXIT_PROBE = textwrap.dedent("""
    import atexit, gc, sys, tempfile, weakref
    from pathlib import Path

    out = Path(sys.argv[1])
    tmp = tempfile.TemporaryDirectory()
    Path(tmp.name, "x").write_text("x")
    (out / "tmp").write_text(tmp.name)

    class Node:  # cyclic garbage with a finaliser: what the last collection would have found
        def __del__(self):
            pass

    a, b = Node(), Node()
    a.other, b.other = b, a
    weakref.finalize(a, lambda: (out / "finalized").write_text("yes"))
    del a, b
    gc.disable()  # the cycle stays for the exit to find
    atexit.register(lambda: (out / "frozen").write_text(str(gc.get_freeze_count())))  # runs after skip's handler
    if sys.argv[2] == "skip":
        from ringscan.kernels.process import skip_final_collection
        skip_final_collection()
        skip_final_collection()  # registered once
""")


@pytest.mark.parametrize("mode", ["skip", "plain"])
def test_skip_final_collection_freezes_at_exit_after_later_handlers(tmp_path, mode):
    """The process ends as before (status 0, the atexit handlers registered before the call, weakref
    finalisers and temporary folders all run), with every object left frozen for the exit: no last pass."""
    r = subprocess.run([sys.executable, "-c", EXIT_PROBE, str(tmp_path), mode], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    frozen = int((tmp_path / "frozen").read_text())
    assert (frozen > 1000) if mode == "skip" else frozen == 0
    assert (tmp_path / "finalized").read_text() == "yes"  # weakref.finalize's atexit pass still ran
    assert not Path((tmp_path / "tmp").read_text()).exists()  # the temporary folder was removed


def test_uncached_kernel_modules_reads_warps_kernel_cache(tmp_path, monkeypatch):
    """An empty kernel cache holds none of ringscan's kernel modules (those with kernels: not
    runtime.py, which has none); checking compiles nothing into it."""
    import warp as wp

    from ringscan.kernels.runtime import uncached_kernel_modules

    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    cold = uncached_kernel_modules("cpu")
    assert {"ringscan.kernels.raytrace", "ringscan.kernels.ring_lines", "ringscan.kernels.triangulation"} <= set(cold)
    assert "ringscan.kernels.runtime" not in cold
    assert not any(tmp_path.iterdir())


INIT_RACE = textwrap.dedent("""
    import threading
    import warp._src.context as ctx
    from ringscan.kernels.runtime import init_warp

    made = []
    real = ctx.Runtime.__init__

    def counted(self, *a, **k):  # Warp's runtime, counted as it is made
        made.append(threading.get_ident())
        real(self, *a, **k)

    ctx.Runtime.__init__ = counted
    gate = threading.Barrier(4)

    def start():
        gate.wait()
        init_warp()

    threads = [threading.Thread(target=start) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print(len(made))
""")


def test_threads_that_start_warp_at_once_start_it_once():
    # Two cameras of an import start Warp on their own threads; a second wp.init() there made a second
    # runtime and marked every module modified while the other thread loaded one (a KeyError out of
    # Warp's Module.load on a first run).
    r = subprocess.run([sys.executable, "-c", INIT_RACE], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == "1"
