"""``LRU``: the bounded cache behind the road-edge grids, IDM plans and training shards."""

from tbsim_env.core.lru import LRU


def test_the_least_recently_used_entry_goes_first():
    lru = LRU(2)
    lru.put("a", 1), lru.put("b", 2)
    assert lru.get("a") == 1  # "a" is now the most recent
    lru.put("c", 3)
    assert lru.get("b") is None and lru.get("a") == 1 and lru.get("c") == 3
    assert len(lru) == 2


def test_no_bound_keeps_everything_and_clear_empties():
    lru = LRU(None)
    for k in range(100):
        lru.put(k, k)
    assert len(lru) == 100 and lru.get(0) == 0
    lru.clear()
    assert len(lru) == 0 and lru.get(0) is None
