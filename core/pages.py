"""Process memory while a large stage runs: numpy's large arrays on ordinary pages
(:func:`without_huge_pages`), and the free memory worker threads' heaps keep given back
(:func:`release_free_memory`).

numpy asks the kernel for transparent huge pages (``madvise``) for every large array it
allocates. Where the kernel then compacts memory to find them on the first touch of each
(``/sys/kernel/mm/transparent_hugepage/defrag`` = ``madvise``, as on this project's machines),
a stage that makes many large temporaries pays for it in system time, more than the fewer TLB
misses save: the 3 MP texture's assembly and solve took 7.7–7.9 s of CPU with ordinary pages
against 8.2–9.2 s with huge pages (system time 2.0 against 2.8–3.7 s), its tiles 10.2–10.4
against 11.0–11.2 s, back to back at a load of 2 (docs/texture.md, "Large photographs").
"""
from __future__ import annotations

import contextlib
from typing import Iterator


@contextlib.contextmanager
def without_huge_pages() -> Iterator[None]:
    """numpy's new large arrays without the huge-page request inside the block; the previous
    setting is restored after it. A numpy without the switch runs the block unchanged."""
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:  # numpy < 2 or a build without it
        yield
        return
    previous = _set_madvise_hugepage(False)
    try:
        yield
    finally:
        _set_madvise_hugepage(previous)


def release_free_memory() -> None:
    """Give the free memory of every malloc heap back to the system (glibc's ``malloc_trim``).

    Worker threads allocate from heaps of their own, which keep what was freed in them: after
    the tiles of a 3 MP texture, reduced in two threads, 0.3 GB stayed resident through the
    assembly (the stage's peak: 2.58–2.70 GB against 2.24–2.36 GB in one thread). Nothing
    happens where the C library has no ``malloc_trim``.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
