"""Load Mitsuba 3 once, with the variant this machine can run.

``llvm_ad_rgb`` on the CPU (needs a system LLVM >= 16; Debian's libllvm19, see the Makefile), or the
variant named by ``REFLAB_MITSUBA_VARIANT`` (``cuda_ad_rgb`` on a GPU machine).
"""
from __future__ import annotations

import functools
import os


@functools.lru_cache(maxsize=None)
def mitsuba():
    """Return the ``mitsuba`` module with its variant set."""
    import mitsuba as mi

    variant = os.environ.get("REFLAB_MITSUBA_VARIANT", "llvm_ad_rgb")
    try:
        mi.set_variant(variant)
    except (ImportError, AttributeError, RuntimeError) as exc:
        raise RuntimeError(
            f"Mitsuba variant {variant!r} is not available ({exc}). The CPU variant needs LLVM >= 16 "
            "(Debian/Ubuntu: apt-get install libllvm19, or set DRJIT_LIBLLVM_PATH)."
        ) from exc
    return mi
