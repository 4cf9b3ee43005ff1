"""tools.bench.core: the bench's default scene is found where the docs say."""

from pathlib import Path

from ringscan.tools.bench.core import default_bench_scene


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
