"""The render-speed benchmark (``scenesig bench render``): JSON alone on stdout, the table on
stderr, the same JSON in ``--json``; every condition asked for is timed."""
import json


def test_bench_prints_json_on_stdout_and_writes_it(tmp_path, capsys):
    from scenesig.benchmarks.render import main

    out = tmp_path / "render.json"
    assert main(["--preset", "tiny", "--frames", "3", "--conditions", "sunny,night", "--json", str(out)]) == 0
    captured = capsys.readouterr()
    res = json.loads(captured.out)          # stdout is the JSON and nothing else
    assert res == json.loads(out.read_text())
    assert set(res["conditions"]) == {"sunny", "night"}
    assert res["frames"] == 3 and res["size"] == [320, 240]
    for r in res["conditions"].values():
        assert r["render_fps"] > 0 and 0 < r["with_jpeg_fps"] <= r["render_fps"]
    assert "frames/s" in captured.err
