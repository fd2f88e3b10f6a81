"""The Section every section module returns, and the numbers it writes: read (``floats``) and
formatted (``num``, ``mm``, ``pm``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Section:
    """A report section: an id (an anchor), a title, a one-line lead and its blocks in order."""

    id: str
    title: str
    lead: str = ""
    blocks: list = field(default_factory=list)

    def kv(self, rows, caption: str = "") -> None:
        rows = [(k, v) for k, v in rows if v not in (None, "", [])]
        if rows:
            self.blocks.append({"kind": "kv", "rows": rows, "caption": caption})

    def table(self, head, rows, caption: str = "") -> None:
        if rows:
            self.blocks.append({"kind": "table", "head": list(head), "rows": rows, "caption": caption})

    def figure(self, src: str | None, caption: str, id: str | None = None) -> None:
        if src:
            self.blocks.append({"kind": "figure", "src": src, "caption": caption, "id": id})

    def images(self, items, caption: str = "") -> None:
        """A row of pictures: (src, caption) for images shown pixel for pixel, (src, caption, True) for plots."""
        items = [{"src": it[0], "caption": it[1], "plot": len(it) > 2 and it[2]} for it in items if it[0]]
        if items:
            self.blocks.append({"kind": "images", "items": items, "caption": caption})

    def note(self, text: str, level: str = "info") -> None:
        self.blocks.append({"kind": "note", "text": text, "level": level})


def num(x, digits: int = 4) -> str:
    """A number or a list of numbers, ``digits`` significant; '–' for None/NaN."""
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(num(v, digits) for v in x) + "]"
    if isinstance(x, bool) or x is None:
        return "–" if x is None else str(x)
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return "–" if not math.isfinite(x) else f"{x:.{digits}g}"
    return str(x)


def mm(x) -> str:
    """A length in millimetres, to the micrometre."""
    return f"{x:.3f}" if isinstance(x, (int, float)) and math.isfinite(x) else "–"


def pm(value, sigma, digits: int = 4) -> str:
    """'value ± sigma' (per band for lists); the value alone where σ is unknown."""
    if sigma is None or (isinstance(sigma, list) and all(s is None for s in sigma)):
        return num(value, digits)
    if isinstance(value, list) and isinstance(sigma, list):
        return "[" + ", ".join(pm(v, s, digits) for v, s in zip(value, sigma)) + "]"
    if isinstance(value, (int, float)) and isinstance(sigma, (int, float)):
        return f"{num(value, digits)} ± {num(sigma, 2)}"
    return num(value, digits)


def span(lo, hi) -> str:
    """A plausible range as 'lo–hi' (3 significant digits)."""
    return f"{num(lo, 3)}–{num(hi, 3)}"


def pm_range(value, sigma, rng, undetermined=False, digits: int = 4, log: bool = False) -> str:
    """``pm`` for a value with a plausible range ``rng`` = (lo, hi) or None: a value the fit calls
    ``undetermined`` (a bool, or one per band), or whose σ is wider than its range, reads
    'undetermined (plausible range lo–hi)' (per band for lists), never 'value ± σ' with a σ that
    says nothing. ``log``: a parameter searched in log2 (ns, α), whose σ is compared in log2 too
    (σ / (value ln 2) against log2(hi / lo))."""
    if rng is None:
        return pm(value, sigma, digits)
    lo, hi = rng
    if isinstance(value, list):
        sig = sigma if isinstance(sigma, list) and len(sigma) == len(value) else [sigma] * len(value)
        und = undetermined if isinstance(undetermined, list) and len(undetermined) == len(value) else [undetermined] * len(value)
        parts = [pm_range(v, s, rng, u, digits, log) for v, s, u in zip(value, sig, und)]
        return parts[0] if len(set(parts)) == 1 and parts[0].startswith("undetermined") else "[" + ", ".join(parts) + "]"
    wide = isinstance(sigma, (int, float)) and (not math.isfinite(sigma) or sigma > hi - lo)
    spread = None  # σ in log2 units, of a parameter searched in log2
    if log and isinstance(sigma, (int, float)) and isinstance(value, (int, float)) and value > 0:
        spread = sigma / (value * math.log(2))
        wide = wide or (lo > 0 and spread > math.log2(hi / lo))
    if (any(undetermined) if isinstance(undetermined, list) else bool(undetermined)) or wide:
        return f"undetermined (plausible range {span(lo, hi)})"
    if spread is not None:
        # Its σ is symmetric in log2: one σ is a factor, and the upward tail is the longer.
        return f"{pm(value, sigma, digits)} (×/÷ {num(2.0 ** spread, 3)})"
    return pm(value, sigma, digits)


def floats(x) -> np.ndarray | None:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return a if a.size and np.all(np.isfinite(a)) else None
