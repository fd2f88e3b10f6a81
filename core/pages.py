"""numpy's large arrays on ordinary pages while a stage runs (:func:`without_huge_pages`).

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
