"""surveys.cache.LRUCache: the one LRU cache (map store, detector, point-feature method)."""
import threading

from scenesig.surveys.cache import LRUCache


def test_lru_order_and_bound():
    c = LRUCache(2)
    c.put(1, "a")
    c.put(2, "b")
    assert c.get(1) == "a"          # 1 is now the most recent
    c.put(3, "c")                   # drops 2, the least recently used
    assert c.keys() == [1, 3] and 2 not in c and len(c) == 2
    assert c.get(2) is None and (c.hits, c.misses) == (1, 1)
    c.discard(1)
    assert c.keys() == [3]
    c.clear()
    assert len(c) == 0


def test_size_zero_keeps_nothing():
    c = LRUCache(0)
    c.put("k", 1)
    assert c.get("k", "none") == "none" and len(c) == 0


def test_threads_never_exceed_the_bound():
    c = LRUCache(5)

    def work(base):
        for i in range(500):
            c.put(base + i % 20, i)
            c.get(base + (i * 7) % 20)

    th = [threading.Thread(target=work, args=(100 * k,)) for k in range(4)]
    for t in th:
        t.start()
    for t in th:
        t.join()
    assert len(c) <= 5
