"""``scenesig bench places``: the retrieval protocols on GRIEF data and recall@N."""
import json

import numpy as np

from scenesig.benchmarks.places import protocols, recall_at, run_benchmark


def test_recall_at_counts_within_tolerance():
    scores = np.array([[0.9, 0.1, 0.5, 0.0],      # ranking 0, 2, 1, 3 for the first three queries
                       [0.9, 0.1, 0.5, 0.0],
                       [0.9, 0.1, 0.5, 0.0],
                       [0.0, 0.0, 0.0, 1.0]])
    truth = np.array([0, 1, 3, 3])
    r = recall_at(scores, truth, 1, 6)
    # truth 0 and 1: place 0 within one at rank 1; truth 3: place 2 at rank 2; recall@N beyond 4 places stays
    assert r.tolist() == [0.75, 1.0, 1.0, 1.0, 1.0, 1.0]
    assert recall_at(scores, truth, 0, 4)[0] == 0.5


def test_protocols_season_and_stromovka(grief_root):
    from scenesig.surveys.grief import load

    season = protocols(load(grief_root / "season"))
    assert len(season) == 1 and len(season[0].queries) == 101 and season[0].tolerance == 1
    assert all(s == 0 for _, s in season[0].map_images) and all(s == 1 for _, s in season[0].queries)
    strom = protocols(load(grief_root / "stromovka"))
    assert len(strom) == 12 and all(len(p.queries) == 5 and p.tolerance == 0 for p in strom)
    # the query session is never in its map
    assert all(all(s != p.live for _, s in p.map_images) for p in strom)


def test_hog_on_stromovka_writes_the_schema(grief_root, tmp_path):
    doc = run_benchmark(grief_root / "stromovka", ["hog"], tmp_path / "p.json", progress=False)
    disk = json.loads((tmp_path / "p.json").read_text())
    assert set(disk) >= {"dataset", "queries", "places", "tolerance", "methods"}
    assert disk["queries"] == 60 and disk["places"] == 5 and disk["tolerance"] == 0
    m = disk["methods"]["hog"]
    assert {"recall_at_1", "recall_at_5", "seconds_per_query"} <= set(m)
    assert 0.2 < m["recall_at_1"] <= m["recall_at_5"] == 1.0       # 5 places: all within the 5 best
    assert (tmp_path / "places_stromovka.png").is_file() and doc == disk
