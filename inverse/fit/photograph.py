"""The input photograph of the fit: its checks, its saturated pixels, its noise (docs/method.md §3)."""
from __future__ import annotations

import numpy as np

from reflab.core.images import clip_level
from reflab.core.workspace import WorkspaceError
from reflab.inverse.forward.factorization import BANDS


#: At least this many pixel values at the image maximum make a clipped (saturated) plateau.
PLATEAU = 3


def check_image(image, width: int, height: int, path="input image") -> np.ndarray:
    """Validate the input photograph against the camera and return it as float64 (H, W, 3).

    Raises
    ------
    WorkspaceError
        Size different from camera.json, or not a photograph (:func:`reflab.core.images.check_radiance`:
        NaN, mostly negative, all black); noise-level negative values are kept.
    """
    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[:2] != (height, width):
        raise WorkspaceError(path, "size", f"{width}x{height} RGB as in camera.json",
                             got=f"{image.shape[1]}x{image.shape[0]}" if image.ndim >= 2 else image.shape)
    from reflab.core.images import check_radiance

    return check_radiance(image, path)


def saturated_pixels(image, level: float | None = None) -> np.ndarray:
    """Pixels (H*W,) bool with any band at the saturation level.

    Parameters
    ----------
    image : (H, W, 3) array_like
    level : float, optional
        Clipping level. By default the image maximum counts as clipped when at least
        :data:`PLATEAU` pixel values sit exactly on it (a sensor or 16-bit file clips to a plateau;
        a rendered or unclipped highlight has one brightest value).
    """
    flat = np.asarray(image, dtype=np.float64).reshape(-1, BANDS)
    if level is None:
        level = clip_level(flat, PLATEAU)
        if level is None:
            return np.zeros(len(flat), dtype=bool)
    return np.any(flat >= level, axis=1)


def image_noise(image, used=None) -> np.ndarray:
    """Gaussian noise σ per band estimated from one image (Immerkær 1996, median form).

    The 3×3 mask ``[1 −2 1; −2 4 −2; 1 −2 1]`` (a product of two second differences) cancels
    shading that is locally linear or quadratic along rows and columns, and sends white noise of
    σ to σ·6; the median of its absolute response over 0.6745 is robust to edges and highlights.

    Parameters
    ----------
    image : (H, W, 3) array_like
    used : (H, W) bool, optional
        Pixels to trust (e.g. not saturated); a mask response counts only where all 9 are used.

    Returns
    -------
    (3,) ndarray
        0 where no 3×3 window is available.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.shape[0] < 3 or img.shape[1] < 3:
        return np.zeros(BANDS)
    row = img[:, :-2] - 2.0 * img[:, 1:-1] + img[:, 2:]
    resp = row[:-2] - 2.0 * row[1:-1] + row[2:]  # (H-2, W-2, 3)
    ok = np.ones(resp.shape[:2], dtype=bool)
    if used is not None:
        u = np.asarray(used, dtype=bool)
        for dv in range(3):
            for du in range(3):  # 9 shifted views of the mask, not a pixel loop
                ok &= u[dv:dv + resp.shape[0], du:du + resp.shape[1]]
    if not ok.any():
        return np.zeros(BANDS)
    return np.median(np.abs(resp[ok]), axis=0) / (0.6745 * 6.0)


#: Noise estimated once per image over its usable pixels (:func:`remember_noise`), by ``id``
#: with a weak reference that says the image is still that one.
_NOISE: dict = {}


def remember_noise(image, usable=None) -> np.ndarray:
    """:func:`image_noise` of ``image`` over its ``usable`` (H·W,) pixels, kept for every fit that
    reads some of its pixels (:func:`known_noise`): a fit reading a sample of the pixels
    (:mod:`reflab.inverse.fit.sampling`) has too few whole 3×3 windows of them for the estimate."""
    import weakref

    img = np.asarray(image)
    sigma = image_noise(img, None if usable is None else np.asarray(usable, dtype=bool).reshape(img.shape[:2]))
    for key in [k for k, (ref, _) in _NOISE.items() if ref() is None]:
        del _NOISE[key]
    _NOISE[id(img)] = (weakref.ref(img), sigma)
    return sigma


def known_noise(image) -> np.ndarray | None:
    """The noise :func:`remember_noise` kept for this very image object, else None."""
    hit = _NOISE.get(id(image))
    return hit[1] if hit is not None and hit[0]() is image else None


def read_photograph(photo, saturation: float | None = None):
    """A photograph's image, checked against its camera (:func:`check_image`), and its saturated
    pixels (:func:`saturated_pixels`); every pixel saturated raises WorkspaceError naming the file."""
    from reflab.core.images import read_image

    img = check_image(read_image(photo.image), photo.camera.width, photo.camera.height, photo.image)
    sat = saturated_pixels(img, saturation)
    if sat.all():
        raise WorkspaceError(photo.image, "pixels", "some pixels below the saturation level", got="every pixel saturated")
    return img, sat


def stack_photographs(workspace, scene, depth: int, *, saturation: float | None = None, single: bool = False,
                      task=None, log=None, further: int = 0, above: int = 0, background: bool = False):
    stack, image, saturated, photos = _stack_photographs(workspace, scene, depth, saturation=saturation, single=single,
                                                         task=task, log=log, further=further, above=above,
                                                         background=background)
    if len(photos) > 1 and isinstance(stack.trees.stats, dict):
        # Each photograph's own noise (a brighter exposure, a highlight that sets the scale): the
        # diagnosis judges each photograph's misfit against it (diagnosis.mismatched_photographs).
        stack.trees.stats["block_noise"] = [
            image_noise(part, ~saturated[stack.pixels(i)].reshape(part.shape[:2])).tolist()
            for i, part in enumerate(stack.split(image))]
    return stack, image, saturated, photos


def _stack_photographs(workspace, scene, depth: int, *, saturation: float | None = None, single: bool = False,
                       task=None, log=None, further: int = 0, above: int = 0, background: bool = False):
    """The workspace's photographs (the reference and ``inputs/``, or the reference alone with
    ``single``) checked, their trees built or read from the cache, stacked into one system
    (:mod:`reflab.inverse.forward.photographs`).

    With ``further`` > 0 and more than ``above`` usable pixels in all the photographs together (a
    fit that samples), a further photograph's trees are built only for a uniform share of its
    pixels, tiles holding about ``further`` of its usable ones (:func:`reflab.inverse.fit.sampling.tiles`;
    never cached: a sample) where that is at most :data:`reflab.inverse.fit.sampling.MAX_SHARE` of
    them, and ``stack.reach`` holds each pixel's probability to be among them; the others count as
    unusable. The reference keeps every pixel's trees.

    Returns
    -------
    stack : reflab.inverse.forward.photographs.Stack
    image : (H, W, 3) float64
        The stacked photograph.
    saturated : (H·W,) bool
        Saturated pixels (each photograph's own clipping level), padding included.
    photos : list of Photograph

    ``background``: the trees cache files are written on a thread
    (:func:`reflab.inverse.forward.trees.trees_for_workspace`); the caller waits for them
    (:func:`reflab.inverse.forward.trees.wait_for_saves`) before it returns.
    """
    from reflab.inverse.forward.photographs import load_photographs, stack_trees
    from reflab.inverse.forward.trees import trees_for_workspace

    photos = load_photographs(workspace, reference_only=single)
    images, masks, trees = [], [], []
    for photo in photos:
        img, sat = read_photograph(photo, saturation)
        images.append(img)
        masks.append(sat)
    shares = [None] * len(photos)
    if further > 0 and len(photos) > 1 and sum(int((~m).sum()) for m in masks) > int(above):
        from reflab.inverse.fit import sampling

        # The fit reads a sample anyway: a further photograph's trees only where it may draw it.
        shares = [None] + [sampling.tiles(~m.reshape(p.camera.height, p.camera.width), further, sampling.SEED + i)
                           for i, (p, m) in enumerate(zip(photos[1:], masks[1:]), start=1)]
        shares = [s if s is not None and s[1] <= sampling.MAX_SHARE else None for s in shares]
    if not any(s is not None for s in shares):
        for photo in photos:
            trees.append(trees_for_workspace(workspace, scene, photo.camera, photo.lights, depth=depth, log=log,
                                             task=task, background=background))
        stack = stack_trees(trees, [p.lights for p in photos], [p.name for p in photos])
        image = stack.image(images)
        if len(photos) == 1:
            return stack, image, masks[0], photos
        seen = np.zeros(stack.width * stack.height, dtype=bool)
        seen[stack.trees.pixel] = True
        return stack, image, _unusable(stack, masks, seen), photos
    return _stack_shares(workspace, scene, depth, photos, images, masks, shares, task, log, background)


def _unusable(stack, masks, seen) -> np.ndarray:
    """(H·W,) the stacked photographs' saturated pixels, padding, and a further photograph's
    pixels that see no surface (``seen`` False)."""
    saturated = np.ones(stack.width * stack.height, dtype=bool)  # padding counts as unusable
    for i, sat in enumerate(masks):
        saturated[stack.pixels(i)] = sat
    # A further photograph's pixels where the model sees no surface (the table top beyond the
    # reconstructed ground, the room) say nothing about the materials: left out. The reference
    # keeps them, as the single-photograph fit always has (its diagnosis counts them).
    further = np.ones_like(saturated)
    further[stack.pixels(0)] = False
    return saturated | (further & ~seen)


def _stack_shares(workspace, scene, depth, photos, images, masks, shares, task, log, background=False):
    """:func:`stack_photographs` with further photographs' trees built for ``shares`` (pixels, q)
    of their pixels, and for the colour lobes' uniform sample of each textured surface
    (:func:`reflab.inverse.fit.sampling.even_of`, drawn on every pixel's first seen surface as
    from whole trees: the same pixels), which ``stack.reach`` leaves at 0: the fit does not draw them."""
    from reflab.inverse.fit import sampling
    from reflab.inverse.forward.photographs import stack_trees
    from reflab.inverse.forward.trees import first_surfaces, seen_first, trees_for_workspace, trees_of_pixels

    whole = [None if share is not None else trees_for_workspace(workspace, scene, photo.camera, photo.lights,
                                                                depth=depth, log=log, task=task, background=background)
             for photo, share in zip(photos, shares)]
    width = max(int(p.camera.width) for p in photos)
    row0 = np.cumsum([0] + [int(p.camera.height) for p in photos])
    first = np.full(width * int(row0[-1]), -1, dtype=np.int64)
    usable = np.zeros(len(first), dtype=bool)
    for i, (photo, sat, t) in enumerate(zip(photos, masks, whole)):
        w, h = int(photo.camera.width), int(photo.camera.height)
        if t is not None:
            mine = seen_first(t, w * h)
        else:
            mine = first_surfaces(scene, photo.camera)
        v, u = np.divmod(np.arange(w * h), w)
        first[(v + row0[i]) * width + u] = mine
        usable[(v + row0[i]) * width + u] = ~np.asarray(sat, dtype=bool).reshape(-1)
    even = sampling.even_of(first, usable & (first >= 0), row0[:-1] * width,
                            [i for i, s in enumerate(scene) if s.textured])
    trees = []
    for i, (photo, share, t) in enumerate(zip(photos, shares, whole)):
        if t is None:
            w = int(photo.camera.width)
            block = even[row0[i] * width:row0[i + 1] * width].reshape(-1, width)[:, :w].reshape(-1)
            t = trees_of_pixels(scene, photo.camera, photo.lights, np.union1d(share[0], np.flatnonzero(block)),
                                depth=depth, task=task)
        trees.append(t)
    stack = stack_trees(trees, [p.lights for p in photos], [p.name for p in photos])
    stack.reach = np.zeros(stack.width * stack.height)
    for i, share in enumerate(shares):
        if share is None:
            stack.reach[stack.pixels(i)] = 1.0
        else:
            stack.reach[stack.pixels(i)[share[0]]] = share[1]
    stack.even = even
    return stack, stack.image(images), _unusable(stack, masks, first >= 0), photos
