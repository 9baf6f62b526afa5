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


def test_shortlist_size_takes_counts_and_shares():
    from scenesig.benchmarks.places import shortlist_size

    assert shortlist_size(10, 101) == 10 and shortlist_size(500, 101) == 101
    assert shortlist_size("40%", 101) == 40 and shortlist_size("40%", 5) == 2 and shortlist_size(0.4, 5) == 2
    assert shortlist_size("1%", 5) == 1
    for bad in (0, "0%", "150%"):
        with np.testing.assert_raises(ValueError):
            shortlist_size(bad, 10)


def test_sequence_scores_follow_the_diagonal():
    """signatures-seq: a query is put at the place whose predecessors verified at the preceding
    places, even when its own verification prefers a look-alike."""
    from scenesig.benchmarks.places import sequence_scores, single_scores

    P = 6
    V = np.full((4, P), 0.1)
    for q in range(4):
        V[q, q + 1] = 0.8                  # truth: query q is place q + 1
    V[3, 0] = 0.9                          # query 3 alone prefers place 0 (a look-alike)
    desc = np.zeros((4, P))
    assert np.argmax(single_scores(desc, V)[3]) == 0
    S = sequence_scores(desc, V, 3)
    assert np.argmax(S[3]) == 4 and np.argmax(S[2]) == 3
    # length 1 keeps the single-image order; places outside a shortlist (NaN) count 0
    assert np.argmax(sequence_scores(desc, V, 1)[3]) == 0
    Vn = V.copy()
    Vn[1:3, :] = np.nan
    assert np.argmax(sequence_scores(desc, Vn, 3)[3]) == 0


def test_single_session_protocol(grief_root):
    from scenesig.surveys.grief import load

    prs = protocols(load(grief_root / "stromovka"), "single-session")
    assert len(prs) == 132 and all(len(p.queries) == 5 and len(p.map_images) == 5 for p in prs)
    assert all(p.map_images[0][1] != p.queries[0][1] for p in prs)
    with np.testing.assert_raises(ValueError):
        protocols(load(grief_root / "season"), "single-session")


def test_cli_rejects_a_bad_shortlist(grief_root, tmp_path, capsys):
    from scenesig.benchmarks.places import main

    assert main([str(grief_root / "stromovka"), "--methods", "hog", "--json", str(tmp_path / "p.json"),
                 "--shortlist", "abc"]) == 2
    assert "--shortlist" in capsys.readouterr().err and not (tmp_path / "p.json").exists()
    assert main([str(grief_root / "stromovka"), "--methods", "hog", "--json", str(tmp_path / "p.json"),
                 "--shortlist", "0"]) == 2
    assert not (tmp_path / "p.json").exists()
