"""The captures section: each capture folder's manifest and a few thumbnails."""
from __future__ import annotations

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources, as_dict, as_list
from reflab.app.report.sections.section import Section, num


def _when(stamp) -> str:
    """An ISO 8601 UTC time as 'YYYY-MM-DD HH:MM:SS' (as written when it does not parse)."""
    import datetime

    if not isinstance(stamp, str):
        return "–"
    try:
        t = datetime.datetime.fromisoformat(stamp)
    except ValueError:
        return stamp
    if t.tzinfo is not None:
        t = t.astimezone(datetime.timezone.utc)
    return t.strftime("%Y-%m-%d %H:%M:%S")


def captures_section(src: Sources, thumbs: int = 6) -> Section | None:
    manifests = src.manifests()
    if not manifests:
        return None
    sec = Section("captures", "Captures", "What was photographed, when, and with which exposure (captures/*/manifest.json).")
    rows = []
    for folder, m in manifests.items():
        shots = [s for s in as_list(m.get("shots")) if isinstance(s, dict)]
        exposures = sorted({s.get("exposure") for s in shots if s.get("exposure") is not None})
        sizes = sorted({"x".join(map(str, s.get("size"))) for s in shots if isinstance(s.get("size"), list)})
        cam = as_dict(m.get("camera"))
        rows.append([folder, m.get("kind", folder), m.get("status", "–"), f"{len(shots)} of {len(m['plan']) if isinstance(m.get('plan'), list) else '?'}",
                     _when(m.get("started")), _when(m.get("updated")),
                     ", ".join(num(e) for e in exposures) or "camera's own", ", ".join(sizes) or "–",
                     cam.get("type", "–")])
        if m.get("error"):
            sec.note(f"captures/{folder}: {m['error']}", "bad" if m.get("status") == "stopped" else "warn")
    sec.table(["folder", "kind", "status", "shots", "started (UTC)", "last written", "exposure (s)", "size", "camera"],
              rows)
    for folder, m in manifests.items():
        shots = [s for s in as_list(m.get("shots")) if isinstance(s, dict) and s.get("file")]
        if not shots:
            continue
        pick = [shots[i] for i in sorted(set(np.linspace(0, len(shots) - 1, min(thumbs, len(shots))).round().astype(int)))]
        items = []
        for s in pick:
            img = src.image(src.rel(src.ws.captures / folder / s["file"]))
            if img is None:
                continue
            lamps = s.get("lamps")
            on = "" if not isinstance(lamps, list) else " lamps " + (",".join(str(k) for k, v in enumerate(lamps) if v) or "off")
            angle = f" {num(s.get('angle'), 4)}°" if isinstance(s.get("angle"), (int, float)) else ""
            items.append((F.thumb(F.display(img), 200, 150), f"{s['file']}{angle}{on}"))
        sec.images(items, f"captures/{folder}: {len(pick)} of {len(shots)} shots")
    return sec
