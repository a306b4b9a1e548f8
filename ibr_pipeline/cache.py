"""Per-process memoisation for worker processes: a worker that handles several views of a per-view
stage loads what they share (the global mesh and its ray-casting BVH, a stage's loader) once.

Values live in the process only; a key must change whenever what the value was computed from
changes (file_key: a file's path, size and modification time).
"""
from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path
from typing import Callable, Hashable


def file_key(path: Path | str) -> tuple:
    """(path, inode, size, mtime_ns): changes whenever the file is rewritten. The inode too: the
    workspace replaces files by atomic renames, a new inode even when size and modification time
    come out equal."""
    st = os.stat(path)
    return (str(path), st.st_ino, st.st_size, st.st_mtime_ns)


class ProcessCache:
    """The `maxsize` most recently used values, by key."""

    def __init__(self, maxsize: int):
        if maxsize < 1:
            raise ValueError(f"maxsize must be >= 1, got {maxsize}")
        self.maxsize = maxsize
        self._items: OrderedDict = OrderedDict()

    def get(self, key: Hashable, compute: Callable[[], object]):
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        value = compute()
        self._items[key] = value
        while len(self._items) > self.maxsize:
            self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        self._items.clear()

    def __len__(self) -> int:
        return len(self._items)
