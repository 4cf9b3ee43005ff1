"""tools.bench.core: the bench's default scene is found where the docs say; the memory-floor
line names the run it measures."""

from pathlib import Path

from ringscan.tools.bench.core import default_bench_scene, floor_note


def test_default_scene_is_spot_from_shared_data(shared_data, monkeypatch):
    """`ringscan bench` times Spot from ../shared/data (docs/accuracy.md); after the
    package layout change the path pointed one folder too low and the bench fell back
    to the sphere without saying so."""
    monkeypatch.delenv("RINGSCAN_SHARED_DATA", raising=False)
    scene = default_bench_scene()
    assert Path(scene).name == "odedstein_spot.obj" and Path(scene).is_file()
    assert Path(scene).resolve() == (shared_data / "models" / "odedstein_spot.obj").resolve()


def test_default_scene_without_shared_data_is_the_sphere(tmp_path, monkeypatch):
    monkeypatch.setenv("RINGSCAN_SHARED_DATA", str(tmp_path))
    assert default_bench_scene() == "sphere"


def _run(device, threads, total):
    return {"device": device, "threads": threads, "times": {"total": total}}


def test_floor_note_is_the_cpu_run_or_names_the_device():
    floor = 0.002
    # cpu on every core, cpu on one, cuda:0 (the default order): the CPU's run on every core
    runs = [_run("cpu", 2, 0.028), _run("cpu", 1, 0.05), _run("cuda:0", 2, 0.003)]
    assert floor_note(runs, floor) == "Warp CPU total is 14.0x that floor"
    # --device cuda:0 --device cpu: still the CPU's
    assert floor_note([runs[2], runs[0]], floor) == "Warp CPU total is 14.0x that floor"
    # --device cuda:0 alone: the GPU's, named (it was reported as the CPU's)
    assert floor_note([runs[2]], floor) == "Warp cuda:0 total is 1.5x that floor"
