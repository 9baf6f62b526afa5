"""Speed benchmark (heavy: mines a 31-image 640x480 place)."""
import json

import numpy as np
import pytest

from scenesig.benchmarks.speed import _bank_of, run_from_args


def test_bank_of_draws_with_repetition_only_when_needed():
    from scenesig.signatures.bank import Bank, Classifier
    cs = [Classifier(np.zeros((2, 2, 31), np.float32), float(i), 1, (0, 0, 16, 16), (8, 8), 1.0)
          for i in range(5)]
    bank = Bank(cs)
    rng = np.random.default_rng(0)
    assert sorted(c.bias for c in _bank_of(bank, 5, rng)) == [0, 1, 2, 3, 4]
    assert len(_bank_of(bank, 12, rng)) == 12


@pytest.mark.heavy
def test_speed_bench_targets(tmp_path):
    class Args:
        json = str(tmp_path / "speed.json")
        train_repeats = 2
    assert run_from_args(Args()) == 0
    res = json.loads((tmp_path / "speed.json").read_text())
    runs = res["train_seconds_per_place_runs"]
    assert len(runs) == 2 and res["train_seconds_per_place"] == pytest.approx(sum(runs) / 2, abs=0.011)
    assert res["hog_ms_per_level"] <= 10.0
    assert res["train_seconds_per_place"] <= 30.0
    assert res["detect_ms_per_frame"]["50"] <= 50.0
    assert set(res["detect_ms_per_frame"]) == {"50", "200"} and res["blas"]["library"]
    # CPU time can only be below the wall time of a single-threaded run
    assert 0 < res["train_cpu_seconds_per_place"] <= res["train_seconds_per_place"] * 1.05 + 0.5
    assert set(res["detect_cpu_ms_per_frame"]) == {"50", "200"}
