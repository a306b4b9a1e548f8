"""cache.ProcessCache: LRU by key; file_key changes when a file is rewritten."""
from __future__ import annotations

import os

import pytest

from ibr_pipeline.cache import ProcessCache, file_key


def test_lru_keeps_the_most_recent_and_computes_once():
    calls = []
    c = ProcessCache(2)

    def make(k):
        return lambda: calls.append(k) or k * 10
    assert c.get(1, make(1)) == 10 and c.get(2, make(2)) == 20 and c.get(1, make(1)) == 10
    assert calls == [1, 2]                      # a hit does not recompute
    c.get(3, make(3))                           # evicts 2, the least recently used
    assert len(c) == 2 and c.get(1, make(1)) == 10 and calls == [1, 2, 3]
    c.get(2, make(2))
    assert calls == [1, 2, 3, 2]
    c.clear()
    assert len(c) == 0
    with pytest.raises(ValueError):
        ProcessCache(0)


def test_file_key_follows_rewrites(tmp_path):
    f = tmp_path / "g.ply"
    f.write_text("a")
    k = file_key(f)
    assert file_key(f) == k
    f.write_text("bb")
    os.utime(f, ns=(1, 1))
    assert file_key(f) != k
