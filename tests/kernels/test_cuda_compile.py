"""Every Warp module compiles for CUDA (sm_90, PTX through NVRTC), even on a
machine with no GPU, so CUDA-only breakage is caught here. The PTX goes to Warp's
kernel cache (keyed by the code's hash): a module is compiled the first time its code
is seen and whenever it changes."""

import importlib
import pkgutil
from pathlib import Path

import pytest
import warp as wp

import ringscan.kernels as kernels_pkg

# Warp's start-up, the processes' host policy, the Samples dataclass, the stages' settings, the response tables:
# no Warp code
HOST_ONLY = {"runtime", "process", "samples", "settings", "response"}
KERNEL_MODULES = sorted(
    m.name for m in pkgutil.iter_modules(kernels_pkg.__path__) if not m.name.startswith("_") and m.name not in HOST_ONLY
)


def test_kernel_modules_found():
    assert {"geometry", "ring_labels", "ring_sampling", "triangulation"} <= set(KERNEL_MODULES)
    found = {m.name for m in pkgutil.iter_modules(kernels_pkg.__path__)}
    assert HOST_ONLY <= found, "a host-only module was renamed: update HOST_ONLY"


@pytest.mark.parametrize("name", KERNEL_MODULES)
def test_module_compiles_for_cuda(name, tmp_path):
    from ringscan.kernels import init_warp

    init_warp()
    mod = importlib.import_module(f"ringscan.kernels.{name}")
    wmod = wp.get_module(mod.__name__)
    if not wmod.kernels:
        # helpers only (@wp.func, structs): they compile inside the modules that use them
        assert wmod.functions or wmod.structs, f"{name} has no Warp code"
        return
    try:
        # Into Warp's kernel cache, as every CPU kernel of the suite: the PTX is named by the hash of the
        # module's code (its functions from other modules included), options and Warp version, so it is
        # compiled again whenever any of them changes, and reused (not recompiled) while none does.
        paths = wp.compile_aot_module(mod, device=None, arch=90, use_ptx=True)
        ptx = [Path(p) for p in paths or ()]
        if not ptx:  # a Warp that returns no paths: into a folder of our own, looked in
            wp.compile_aot_module(mod, device=None, arch=90, module_dir=tmp_path, use_ptx=True)
            ptx = sorted(tmp_path.rglob("*.ptx"))
    except RuntimeError as e:
        if "NVRTC" in str(e) or "nvrtc" in str(e):
            pytest.skip(f"NVRTC is not available in this Warp build: {e}")
        raise
    assert ptx and all(p.suffix == ".ptx" and p.stat().st_size > 0 for p in ptx), ptx
    text = ptx[0].read_text(errors="replace")
    assert ".target sm_90" in text
