"""Profile benchmarks: stage timing is exclusive, and both profiles run end to end and report their stages."""
import json

import numpy as np
from pipeline_world import make_live_run, make_map

from scenesig.benchmarks import profile_localise, profile_mining
from scenesig.benchmarks._stages import StageTimer


class _Clock:
    """A fake clock: timed code advances it by known amounts."""

    def __init__(self):
        self.t = 0.0

    def perf_counter(self):
        return self.t

    thread_time = perf_counter


_CLOCK = _Clock()


class _Work:
    @staticmethod
    def inner():
        _CLOCK.t += 3.0

    @classmethod
    def outer(cls):
        _CLOCK.t += 1.0
        cls.inner()


def test_stage_timer_is_exclusive_and_restores(monkeypatch):
    from scenesig.benchmarks import _stages

    monkeypatch.setattr(_stages, "time", _CLOCK)
    timer = StageTimer()
    orig_outer, orig_inner = _Work.__dict__["outer"], _Work.__dict__["inner"]
    with timer.patch((_Work, "inner", "b"), (_Work, "outer", "a")):
        _Work.outer()
        _Work.inner()
    assert _Work.__dict__["outer"] is orig_outer and _Work.__dict__["inner"] is orig_inner
    assert timer.calls == {"a": 1, "b": 2}
    # outer is charged its own 1 s, not the 4 s including the inner call it made
    assert timer.seconds == {"a": 1.0, "b": 6.0} and timer.cpu_seconds == {"a": 1.0, "b": 6.0}
    assert {k: dict(v) for k, v in timer.by_thread.items()} == {"a": {"MainThread": [1.0, 1.0]},
                                                               "b": {"MainThread": [6.0, 6.0]}}
    d = timer.as_dict(per=2)
    assert d["b"] == {"ms": 6000.0, "cpu_ms": 6000.0, "calls": 2, "ms_per": 3000.0, "cpu_ms_per": 3000.0}


def test_profile_mining_reports_the_stages():
    from scenesig.localiser.synthetic import synthetic_place

    images, offsets = synthetic_place(4, 128, 96, seed=0)
    res = profile_mining.profile_mining(images, offsets, shapes=6)
    assert res["shapes"] == 6 and res["threads"] == 1
    st = res["stages"]
    for k in ("pyramids", "partitions", "candidates", "negatives", "gram", "svm_kernel", "svm_solve", "fire"):
        assert st[k]["calls"] > 0 and st[k]["ms"] >= 0, k
    covered = sum(v["ms"] for k, v in st.items() if k != "other")
    assert abs(covered + st["other"]["ms"] - 1e3 * res["seconds"]) < 1.0
    json.dumps(res)


def test_profile_localise_reports_the_stages(tmp_path, capsys):
    run = make_live_run(tmp_path / "live", length_m=40.0)
    make_map(tmp_path / "map", length_m=60.0)
    assert profile_localise.main([str(tmp_path / "map"), str(run.root), "--every", "2",
                                  "--json", str(tmp_path / "p.json")]) == 0
    res = json.loads((tmp_path / "p.json").read_text())
    assert res == json.loads(capsys.readouterr().out)
    assert res["detector_frames"] == int(np.ceil(res["frames"] / 2))
    st = res["stages"]
    assert st["image_decode"]["calls"] == res["detector_frames"]
    assert st["graph_update"]["calls"] > 0 and st["snap"]["calls"] >= res["frames"]
    assert "bookkeeping" in st and res["realtime_factor"] > 0
    ref = res["machine_reference_seconds"]                # the machine's speed, before and after
    assert len(ref) == 2 and all(v > 0 for v in ref)
    if res["main_thread_queued_seconds"] is not None:                  # Linux
        assert 0 <= res["main_thread_queued_seconds"] <= res["call_wall_seconds"] + 0.01
        assert res["realtime_factor_unqueued"] >= res["realtime_factor"]


def test_median_ms_unqueued_is_at_most_the_wall_time():
    from scenesig.benchmarks._timing import median_ms_unqueued, queued_seconds

    wall, unqueued = median_ms_unqueued(lambda: sum(range(20000)), repeat=5)
    assert wall > 0
    if queued_seconds() is None:                                       # not Linux
        assert unqueued is None
    else:
        assert 0 <= unqueued <= wall
