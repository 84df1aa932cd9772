"""A thread-safe cache whose entries are built exactly once.

Mitsuba constructs plugins on worker threads (``parallel=True``) and may ask several textures for
the same file at the same time; each entry is built under its own lock while other keys proceed.

Entries can be held weakly (``pack``/``unpack``): the cache then keeps an entry only while
something else — a live texture — still uses it, and forgets it (and its memory) with the last
user, so loading edited files, or scene after scene, does not accumulate images.
"""

from __future__ import annotations

import threading
from typing import Callable


class BuildOnceCache:
    """``get(key, build)``: the cached value, or ``build()`` (once per key, even across threads).

    ``pack(key, value, forget)`` turns a value into what is stored (e.g. weak references, calling
    ``forget()`` when they die) and ``unpack(stored)`` turns it back, or returns None when it is
    gone; by default values are stored as they are (strongly)."""

    def __init__(self, pack: Callable | None = None, unpack: Callable | None = None):
        # re-entrant: a weakly held value may die (and be forgotten) on a thread that holds it
        self._lock = threading.RLock()
        self._entries: dict = {}
        self._key_locks: dict = {}
        self._pack = pack or (lambda key, value, forget: value)
        self._unpack = unpack or (lambda stored: stored)

    def _lookup(self, key):
        """The live value of ``key`` or None (caller holds ``_lock``); drops a dead entry."""
        stored = self._entries.get(key)
        if stored is None:
            return None
        value = self._unpack(stored)
        if value is None:
            self._entries.pop(key, None)
        return value

    def _forget(self, key, stored) -> None:
        with self._lock:
            if self._entries.get(key) is stored:
                del self._entries[key]

    def get(self, key, build):
        with self._lock:
            value = self._lookup(key)
            if value is not None:
                return value
            key_lock = self._key_locks.setdefault(key, threading.Lock())
        with key_lock:
            with self._lock:
                value = self._lookup(key)
                if value is not None:
                    return value
            value = build()
            cell = []
            stored = self._pack(key, value, lambda: self._forget(key, cell[0] if cell else None))
            cell.append(stored)
            with self._lock:
                self._entries[key] = stored
                self._key_locks.pop(key, None)
            return value

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()

    def __len__(self) -> int:
        """Live entries."""
        with self._lock:
            for key in list(self._entries):
                self._lookup(key)
            return len(self._entries)
