"""Pictures for the report, each returned as a ``data:image/png;base64,...`` URI (nothing external).

Photographs and maps go through :func:`png_uri` (OpenCV's PNG encoder, no axes); plots are drawn
with matplotlib's Agg backend (:func:`figure_uri`). Heavy modules are imported inside functions.
"""
from __future__ import annotations

import base64

import numpy as np

#: Colours of lamps, surfaces and series, in order (matplotlib's tab10).
COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]


def png_uri(rgb8: np.ndarray) -> str:
    """An 8-bit RGB (H, W, 3) or grey (H, W) array as a PNG data URI."""
    import cv2

    arr = np.ascontiguousarray(rgb8)
    if arr.ndim == 3:
        arr = np.ascontiguousarray(arr[:, :, ::-1])
    ok, buf = cv2.imencode(".png", arr, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise ValueError("could not encode a PNG")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def thumb(rgb8: np.ndarray, width: int = 360, height: int = 200) -> str:
    """An 8-bit picture fitted into ``width`` × ``height`` as a PNG data URI: shrunk by area averaging
    when larger, enlarged by a whole factor (pixels kept square and sharp) when smaller."""
    a = np.asarray(rgb8)
    h, w = a.shape[:2]
    step = int(np.ceil(max(h / height, w / width, 1.0)))
    if step > 1:
        hh, ww = h // step * step, w // step * step
        a = a[:hh, :ww].reshape(hh // step, step, ww // step, step, *a.shape[2:]).mean(axis=(1, 3)).round().astype(np.uint8)
    else:
        k = max(1, min(height // max(h, 1), width // max(w, 1)))
        a = np.repeat(np.repeat(a, k, axis=0), k, axis=1)
    return png_uri(a)


def display(img: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """8-bit sRGB of a linear image (reflab.core.images.to_display; exposure: the 99.5th percentile at 1 by default)."""
    from reflab.core.images import to_display

    return to_display(np.asarray(img, dtype=np.float64), exposure)


def figure_uri(fig) -> str:
    """A matplotlib figure as a PNG data URI (the figure is closed)."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def new_figure(width: float = 6.4, height: float = 3.6, ncols: int = 1):
    """A matplotlib figure on the Agg backend (no display needed) and its axes."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=(width, height), squeeze=False, layout="constrained")
    return fig, list(axes[0])


def heat_with_bar(values: np.ndarray, title: str, label: str, vmax: float | None = None) -> str:
    """A heat map with its colour bar (units on the bar), as a data URI."""
    v = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(v)
    if vmax is None:
        vmax = float(np.percentile(v[finite], 99.5)) if finite.any() else 1.0
    aspect = v.shape[0] / max(v.shape[1], 1)
    fig, (ax,) = new_figure(2.4 / max(aspect, 0.3) + 1.2, 2.4)
    im = ax.imshow(np.ma.masked_invalid(v), cmap="inferno", vmin=0, vmax=max(vmax, 1e-300), interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    bar.set_label(label, fontsize=8)
    bar.ax.tick_params(labelsize=7)
    return figure_uri(fig)


def bars(labels, series: dict, ylabel: str, title: str = "") -> str:
    """Grouped bars: one group per label, one bar per series (name -> values)."""
    fig, (ax,) = new_figure(max(4.0, 0.45 * len(labels) * len(series) + 1.5), 2.8)
    n = max(len(series), 1)
    x = np.arange(len(labels))
    for i, (name, vals) in enumerate(series.items()):
        ax.bar(x + (i - (n - 1) / 2) * 0.8 / n, [np.nan if v is None else v for v in vals], 0.8 / n,
               label=name, color=COLOURS[i % len(COLOURS)])
    ax.set_xticks(x, labels, rotation=30 if max((len(str(l)) for l in labels), default=0) > 6 else 0,
                  ha="right" if max((len(str(l)) for l in labels), default=0) > 6 else "center", fontsize=8)
    ax.set_ylabel(ylabel, fontsize=9)
    ax.tick_params(labelsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    if len(series) > 1:
        ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return figure_uri(fig)
