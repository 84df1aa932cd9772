"""A thread-safe cache whose entries are built exactly once.

Mitsuba constructs plugins on worker threads (``parallel=True``) and may ask several textures for
the same file at the same time; each entry is built under its own lock while other keys proceed.
"""

from __future__ import annotations

import threading


class BuildOnceCache:
    def __init__(self):
        self._lock = threading.Lock()
        self._entries: dict = {}
        self._key_locks: dict = {}

    def get(self, key, build):
        with self._lock:
            if key in self._entries:
                return self._entries[key]
            key_lock = self._key_locks.setdefault(key, threading.Lock())
        with key_lock:
            with self._lock:
                if key in self._entries:
                    return self._entries[key]
            value = build()
            with self._lock:
                self._entries[key] = value
                self._key_locks.pop(key, None)
            return value

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
