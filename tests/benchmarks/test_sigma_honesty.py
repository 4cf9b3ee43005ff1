"""benchmarks/sigma_honesty.py's command line: what it runs for the options given (the runs themselves are
the benchmark's; their tables are in docs/accuracy.md)."""

from tests.support.benchmark_scripts import load_benchmark


def test_a_scene_runs_the_conditions_asked_for_on_it(tmp_path, monkeypatch, capsys):
    """--scene picks the object the conditions render, not the conditions: --only linear-light noise-4
    --scene terrain runs those two on the terrain (it ran every scene's name as a condition, a KeyError),
    and a scene that is neither built in nor a file is refused in one line before anything runs."""
    sh = load_benchmark("sigma_honesty")
    ran = []
    monkeypatch.setattr(sh, "run_condition", lambda name, work, **kw: (ran.append((name, kw["scene"])), ([], {}))[1])
    assert sh.main(["--only", "linear-light", "noise-4", "--scene", "terrain", "--out", str(tmp_path)]) == 0
    assert ran == [("linear-light", "terrain"), ("noise-4", "terrain")]
    ran.clear()
    capsys.readouterr()
    assert sh.main(["--only", "linear-light", "--scene", str(tmp_path / "missing.obj")]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith(f"error: --scene {tmp_path / 'missing.obj'}: neither") and not ran
