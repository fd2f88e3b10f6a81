"""A photograph too large for trees of every pixel: the fit through a binned view (docs/fit.md "Large photographs").

The trees of a photograph take about 2 KB a pixel: a 12-megapixel photograph's would take 25 GB.
The fit reads a sample of the pixels anyway (:mod:`reflab.inverse.fit.sampling`), so above
:data:`LARGE` pixels it builds trees only where it reads:

1. a **view**: the photograph binned f × f (block means) to at most :data:`VIEW` pixels, its camera
   binned with it (:meth:`reflab.calibration.camera.Camera.binned`), and its trees;
2. the **pilot** on the view (a uniform sample, as :func:`reflab.inverse.fit.sampling.pilot`): a seed
   only — a binned pixel is the mean of its block, which the model, evaluated at the block's
   centre, matches only where the light is smooth (not in a sharp highlight);
3. the **pixels read**: view pixels drawn by their evidence under the pilot's parameters
   (:func:`reflab.inverse.fit.sampling.fit_sample`), each replaced by one pixel of its block
   chosen at random, and a uniform share of the photograph's own pixels;
4. their trees, each pixel's own ray (:func:`reflab.inverse.forward.trees.trees_of_pixels`), and the fit on them: the homogeneous
   fit from the pilot's values, then on textured scenes the texture rounds, whose texture comes
   from the view (where directly seen diffuse light dominates, binning is the texels' own
   averaging) and is looked up at the read pixels' nodes.

Every value and σ thus come from full-resolution pixels and their own rays; the view only chooses
them, seeds the fit, and carries the rounds' texture.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from reflab.inverse.fit import sampling

#: Photographs above this many pixels are fitted through a binned view (``reflab fit --large``).
LARGE = 2_000_000
#: The binned view's pixels at most.
VIEW = 500_000


def binning_factor(width: int, height: int, at_most: int | None = None) -> int:
    """The smallest integer f with (W/f)·(H/f) ≤ ``at_most`` (default :data:`VIEW`)."""
    return max(1, int(np.ceil(np.sqrt(width * height / (VIEW if at_most is None else at_most)))))


def bin_image(image, saturated, factor: int):
    """``image`` (H, W, 3) as means of ``factor``² blocks (right and bottom remainders cropped); a
    block is saturated when any of its pixels is. Returns (h, w, 3) and (h·w,) bool."""
    f = int(factor)
    h, w = image.shape[0] // f, image.shape[1] // f
    img = np.asarray(image, dtype=np.float64)[:h * f, :w * f].reshape(h, f, w, f, -1).mean(axis=(1, 3))
    sat = np.asarray(saturated, dtype=bool).reshape(image.shape[:2])[:h * f, :w * f]
    return img, sat.reshape(h, f, w, f).any(axis=(1, 3)).reshape(-1)


def is_large(photos) -> bool:
    """Whether some photograph is above :data:`LARGE` pixels."""
    return any(p.camera.width * p.camera.height > LARGE for p in photos)


@dataclasses.dataclass
class LargeStack:
    """The large photographs' stack of read pixels, their image, what is usable, and the view."""

    stack: object  # reflab.inverse.forward.photographs.Stack of trees_of_pixels (reflab.inverse.forward.trees)
    image: np.ndarray
    saturated: np.ndarray
    photos: list
    sampling: dict


def fit_large(workspace, scene, depth: int, photos, images, saturated, models, *, method="ftbo", maxiter=None,
              max_seconds=None, texture_rounds: int = 2, progress=None, task=None, pixels: int = sampling.PIXELS):
    """Fit photographs too large for trees of every pixel (the module's steps).

    ``photos``, ``images``, ``saturated``: the checked photographs, their (H, W, 3) images and
    (H·W,) saturated masks. Returns (:class:`reflab.inverse.fit.workspace_fit.SceneFit`,
    :class:`LargeStack`).
    """
    from reflab.inverse.fit.photograph import remember_noise
    from reflab.inverse.fit.rounds import fit
    from reflab.inverse.fit.result import SceneFit
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.forward.photographs import stack_trees
    from reflab.inverse.forward.trees import trees_for_workspace, trees_of_pixels

    t0 = time.perf_counter()
    pixels = int(pixels) or sampling.PIXELS
    factors = [binning_factor(p.camera.width, p.camera.height) for p in photos]
    binned = [bin_image(img, sat, f) for img, sat, f in zip(images, saturated, factors)]
    view_cams = [p.camera.binned(f) for p, f in zip(photos, factors)]
    view_trees = [trees_for_workspace(workspace, scene, c, p.lights, depth=depth, task=task)
                  for c, p in zip(view_cams, photos)]
    view = stack_trees(view_trees, [p.lights for p in photos], [p.name for p in photos])
    view_image = view.image([b[0] for b in binned])
    view_usable = np.zeros(view.width * view.height, dtype=bool)
    for i, (_, sat) in enumerate(binned):
        view_usable[view.pixels(i)] = ~sat
    # The pixels read are too sparse for the noise's 3×3 windows: each image's usable ones say it.
    remember_noise(view_image, view_usable)
    t1 = time.perf_counter()
    held = [s.material.given for s in scene]
    textured = [s.textured for s in scene]
    # 2. The pilot on the view: a seed.
    pilot_fac = Factorization(view.trees, models, view.intensities, mask=sampling.pilot(view_usable, pixels))
    if pilot_fac.n_columns == 0:
        from reflab.core.workspace import Workspace, WorkspaceError

        # the same one-line error as the fit of a smaller photograph (workspace_fit.fit_scene)
        raise WorkspaceError(Workspace(workspace).scene, "surfaces", "at least one surface seen by the camera and lit "
                             "by a lamp", got="no pixel sees a lit surface")
    pilot = fit(pilot_fac, view_image, [s.material for s in scene], method, maxiter=maxiter, max_seconds=max_seconds,
                textured=textured, names=scene.names, task=task, held=held, uncertainty=False, reject=False)
    # 3. The pixels read: the view's evidence, each at one pixel of its block, and a uniform share.
    chosen_view, p_view, counts = sampling.fit_sample(view.trees, pilot.materials, view.intensities, view_usable, pixels,
                                              open_lobes=sampling.open_lobes(pilot))
    rng = np.random.default_rng(sampling.SEED + 3)
    bulk_left = int(sampling.BULK * pixels)
    total = sum(int((~sat).sum()) for sat in saturated)
    read, probability, uniform_read = [], [], []
    for i, (photo, f, sat) in enumerate(zip(photos, factors, saturated)):
        b = view.blocks[i]
        px = view.pixels(i)
        sel = px[chosen_view[px]] - b.row0 * view.width
        bv, bu = np.divmod(sel, b.width)
        du, dv = rng.integers(0, f, len(sel)), rng.integers(0, f, len(sel))
        full = (bv * f + dv) * photo.camera.width + (bu * f + du)
        usable = np.flatnonzero(~np.asarray(sat, dtype=bool))
        share = int(round(bulk_left * len(usable) / max(total, 1)))
        bulk = rng.choice(usable, size=min(share, len(usable)), replace=False)
        mine = np.unique(np.concatenate([full[~np.asarray(sat, dtype=bool)[full]], bulk]))
        read.append(mine)
        uniform_read.append(bulk)
        # Its inclusion probability: its view pixel's, shared by the block's f² pixels, or the uniform share's.
        y, x = np.divmod(mine, photo.camera.width)
        inside = (y // f < b.height) & (x // f < b.width)  # the binned view crops the remainders
        p_block = np.zeros(len(mine))
        p_block[inside] = p_view[(b.row0 + y[inside] // f) * view.width + x[inside] // f] / (f * f)
        probability.append(sampling.inclusion(p_block, len(bulk) / max(len(usable), 1)))
    trees = [trees_of_pixels(scene, p.camera, p.lights, r, depth=depth, task=task) for p, r in zip(photos, read)]
    stack = stack_trees(trees, [p.lights for p in photos], [p.name for p in photos])
    image = stack.image(images)
    usable_full = np.zeros(stack.width * stack.height, dtype=bool)
    for i, sat in enumerate(saturated):
        b = stack.blocks[i]
        usable_full.reshape(stack.height, stack.width)[b.row0:b.row0 + b.height, :b.width] = \
            ~np.asarray(sat, dtype=bool).reshape(b.height, b.width)
    remember_noise(image, usable_full)
    del usable_full
    unusable = np.ones(stack.width * stack.height, dtype=bool)
    p_read = np.zeros(stack.width * stack.height)
    even = np.zeros(stack.width * stack.height, dtype=bool)  # the uniform share: for the colour lobes
    for i, (r, sat) in enumerate(zip(read, saturated)):
        b = stack.blocks[i]
        v, u = np.divmod(r, b.width)
        unusable[(v + b.row0) * stack.width + u] = False  # read and not saturated
        p_read[(v + b.row0) * stack.width + u] = probability[i]
        v, u = np.divmod(uniform_read[i], b.width)
        even[(v + b.row0) * stack.width + u] = True
    t2 = time.perf_counter()
    # 4. The fit on the read pixels, from the pilot's values, each row weighed by 1/(its
    # inclusion probability) (Horvitz–Thompson: docs/fit.md "Sampling").
    fit_trees = sampling.weighted(stack.trees, sampling.weights(~unusable, p_read))
    fac = Factorization(fit_trees, models, stack.intensities, mask=~unusable)
    refit = texture_rounds > 0 and np.isin(stack.trees.surface, np.flatnonzero(textured)).any()
    left = None if max_seconds is None else max(max_seconds - pilot.time_s, 1e-3)
    result = fit(fac, image, pilot.materials, method, maxiter=maxiter, max_seconds=left, textured=textured,
                 names=scene.names, task=task, held=held, scan=False, uncertainty=not refit)
    rounds = None
    if refit and not result.message.startswith("stopped"):
        from reflab.inverse.fit.texture_aware import MIN_SHARE, fit_with_texture

        homogeneous_rms = [float(v) for v in result.rms]
        result, records = fit_with_texture(fit_trees, scene, models, stack.intensities, image, result,
                                           mask=~unusable, rounds=texture_rounds, method=method, maxiter=maxiter,
                                           progress=progress, task=task, held=held,
                                           max_seconds=None if left is None else left - result.time_s,
                                           view=(view.trees, view_image, None), colour_mask=even)
        rounds = {"rounds": records, "homogeneous_rms": homogeneous_rms, "min_share": MIN_SHARE}
    elif "complete" in result.stats:
        result = result.stats["complete"]()
    result = dataclasses.replace(result, time_s=result.time_s + pilot.time_s,
                                 evaluations=result.evaluations + pilot.evaluations,
                                 iterations=result.iterations + pilot.iterations)
    report = {"pixels": pixels, "view": [int(f) for f in factors], "pilot": int(pilot_fac.n_rows),
              "evidence": int(counts["evidence"]), "bulk": int(sum(len(r) for r in read) - counts["evidence"]),
              "of": int(total), "read": int(fac.n_rows), "pilot_s": round(pilot.time_s, 6),
              "view_s": round(t1 - t0, 6), "select_s": round(t2 - t1, 6)}
    phases = {"factorization": 0.0, **result.stats.get("phases_s", {}),
              "texture_rounds": round(sum(r["texture_s"] + r["fit_s"] for r in rounds["rounds"]), 6) if rounds else 0.0}
    done = SceneFit(result, fac, rounds, report, phases, int(result.stats.get("scan_evaluations", 0)))
    return done, LargeStack(stack, image, unusable, photos, report)
