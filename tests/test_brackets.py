"""Exposure brackets merged into one linear photograph (reflab.core.brackets, `reflab merge`).

Ground truth: a known radiance image (per second of exposure) spanning 0.05 to 40 with a 50/s
highlight; brackets synthesised from it at 1/64, 1/16, 1/4 and 1 s, (a) linear with shot and read
noise and clipping at 1, written as EXR and as camera RAW (DNG with EXIF times); (b) 8-bit through
a known non-linear response curve (sRGB's curve to the power 1.2) with clipping at 255.
"""
from __future__ import annotations

import numpy as np
import pytest

from reflab.app.cli import main
from reflab.core.images import linear_to_srgb, read_image, write_image

TIMES = [1 / 64, 1 / 16, 1 / 4, 1.0]
HIGHLIGHT = (slice(40, 50), slice(20, 30))


def radiance(h: int = 96, w: int = 128) -> np.ndarray:
    u = np.linspace(0, 1, w)[None, :, None]
    v = np.linspace(0, 1, h)[:, None, None]
    e = 0.05 * (40 / 0.05) ** u * np.array([1.0, 0.8, 0.6]) * (0.7 + 0.3 * v)
    e[HIGHLIGHT] = [50.0, 45.0, 40.0]  # clipped at 1 s and 1/4 s, 0.78 at 1/64 s
    return e


def linear_frames(e, seed=0):
    rng = np.random.default_rng(seed)
    return [np.clip(e * t + rng.normal(size=e.shape) * np.sqrt(1e-7 * e * t + 1e-9), 0, 1) for t in TIMES]


def response(x):
    """The 8-bit camera's response: linear exposure in [0, 1] to code value / 255."""
    return linear_to_srgb(np.clip(x, 0, 1)) ** 1.2


def test_linear_bracket_merges_within_1_percent_and_recovers_a_clipped_highlight(tmp_path):
    e = radiance()
    files = [write_image(tmp_path / f"f{k}.exr", f) for k, f in enumerate(linear_frames(e))]
    assert main(["merge", str(tmp_path / "hdr.exr"), *map(str, files), "--exposures", ",".join(map(str, TIMES)),
                 "--reference-exposure", "0.5"]) == 0
    merged = read_image(tmp_path / "hdr.exr") / 0.5
    rel = np.abs(merged / e - 1)
    # Every pixel is seen unclipped by some frame: within 1 % everywhere (measured 0.65 % at most, median 0.04 %).
    assert rel.max() < 0.01 and np.median(rel) < 0.002
    # The highlight is clipped in the two longest frames: only the short ones give it, within 1 %.
    assert np.all(read_image(files[-1])[HIGHLIGHT] == 1.0) and np.abs(merged[HIGHLIGHT] / e[HIGHLIGHT] - 1).max() < 0.01
    # Without the weights (each frame over its time, averaged) the clipped frames pull it down by half.
    naive = np.mean([read_image(f) / t for f, t in zip(files, TIMES)], axis=0)
    assert np.abs(naive[HIGHLIGHT] / e[HIGHLIGHT] - 1).min() > 0.3


def test_noise_free_linear_bracket_is_exact():
    from reflab.core.brackets import merge_linear

    e = radiance()
    image, unseen, clipped = merge_linear([np.clip(e * t, 0, 1) for t in TIMES], TIMES)
    assert not unseen.any() and not clipped.any() and np.abs(image / e - 1).max() < 1e-12
    # Clipped in every frame: the shortest frame's value stands, a lower bound, and it is flagged.
    image, unseen, clipped = merge_linear([np.clip(e * t, 0, 1) for t in TIMES[1:]], TIMES[1:])
    assert np.array_equal(clipped, e.max(axis=2) * TIMES[1] >= 0.97) and clipped[HIGHLIGHT].all()
    assert np.allclose(image[HIGHLIGHT], 16.0) and np.abs(image / e - 1)[~clipped].max() < 1e-12


def test_raw_bracket_with_exif_times(tmp_path):
    pytest.importorskip("rawpy")
    pytest.importorskip("tifffile")
    from test_inputs_raw import write_dng

    from reflab.core.brackets import MergeOptions, exif_exposure, merge

    e = radiance()
    files = [write_dng(tmp_path / f"f{k}.dng", f, exposure=t) for k, (f, t) in enumerate(zip(linear_frames(e), TIMES))]
    assert exif_exposure(files[0]) == pytest.approx(1 / 64, rel=1e-6)
    r = merge(MergeOptions(tmp_path / "hdr.exr", files))
    assert r.times_from == "EXIF" and r.kind == "linear" and r.clipped == 0
    rel = np.abs(read_image(r.path) / e - 1)[4:-4, 4:-4]  # the demosaic's border left out (test_inputs_raw)
    inner = np.ones(e.shape[:2], bool)
    inner[39:51, 19:31] = False  # the highlight's edge: a demosaic mixes its 50/s with its neighbours' 1/s
    assert np.median(rel) < 0.003 and rel[inner[4:-4, 4:-4]].max() < 0.01
    assert np.abs(read_image(r.path)[42:48, 22:28] / e[42:48, 22:28] - 1).max() < 0.01  # clipped in the long frames


@pytest.mark.parametrize("method", ["debevec"])
def test_8bit_bracket_through_the_recovered_response_curve(tmp_path, method):
    from PIL import Image

    from reflab.core.brackets import MergeOptions, merge

    e = radiance()
    rng = np.random.default_rng(3)
    files = []
    for k, t in enumerate(TIMES):
        codes = np.round(255 * response(e * t * (1 + 0.002 * rng.normal(size=e.shape)))).astype(np.uint8)
        exif = Image.Exif()
        exif[33434] = t  # ExposureTime, read back from the PNG's eXIf chunk
        Image.fromarray(codes).save(tmp_path / f"f{k}.png", exif=exif)
        files.append(tmp_path / f"f{k}.png")
    r = merge(MergeOptions(tmp_path / "hdr.exr", files, response=method))
    assert r.kind == "8-bit" and r.times_from == "EXIF" and r.exposures == pytest.approx(TIMES)
    merged = read_image(r.path)
    codes = np.stack([(255 * response(e * t)).max(axis=2) for t in TIMES])
    seen = np.any((codes > 5) & (codes < 250), axis=0)  # some frame saw it off both ends of the curve
    assert seen.mean() > 0.99
    scale = np.median(merged[seen] / e[seen], axis=0)  # the curve is known up to a scale per band
    rel = np.abs(merged / (e * scale) - 1)[seen]
    # Measured: median 0.45 %, 99th percentile 3.4 %, at worst 8.6 % (where every frame is near an end).
    assert np.median(rel) < 0.01 and np.percentile(rel, 99) < 0.05
    assert np.abs(merged[HIGHLIGHT] / (e[HIGHLIGHT] * scale) - 1).max() < 0.02  # 255 in the long frames
    # The curve is not the identity: treating the codes as linear misses by far more.
    flat = np.mean([codes_k / 255 / t for codes_k, t in zip(codes, TIMES)], axis=0)
    assert np.median(np.abs(flat[seen] / (e.max(axis=2)[seen] * np.median(flat[seen] / e.max(axis=2)[seen])) - 1)) > 0.1


def test_bad_brackets_are_named_in_one_line(tmp_path, capsys):
    e = radiance()
    a, b = (write_image(tmp_path / f"f{k}.exr", np.clip(e * t, 0, 1)) for k, t in enumerate(TIMES[:2]))
    small = write_image(tmp_path / "small.exr", np.clip(e[:48] * 0.25, 0, 1))
    out = str(tmp_path / "hdr.exr")
    cases = [([out, str(a)], "f0.exr: expected two or more exposures of one view (a bracket), got 'a single frame'"),
             ([out, str(a), str(small), "--exposures", "1,2"], "small.exr: expected the size of f0.exr, 128x96, got '128x48'"),
             ([out, str(a), str(b)], "f0.exr: expected an exposure time in its EXIF"),
             ([out, str(a), str(b), "--exposures", "1"], "--exposures: gives 1 times for 2 files"),
             ([out, str(a), str(tmp_path / "gone.exr"), "--exposures", "1,2"], "gone.exr: expected an image file, got 'missing'")]
    for argv, message in cases:
        assert main(["merge", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "hdr.exr").exists()
