"""Images from pixel-intensity trees: arithmetic on the stored nodes, never new ray casting.

Per node ``i`` on surface ``s`` and band ``c`` (docs/architecture.md)::

    radiance_i[c] = P_i[c] · Σ_j basis_i[c, j] · x_s[c, j]
    basis_i[c, j] = fresnel_i · Σ_k visible_ik · intensity_k[c] / dist2_ik · g_j(θ_s; n_i, l_ik, v_i)
    P_i[c]        = Π over the node's path of r_s[c] (reflection) or t_s[c] (transmission)

and a pixel's value is the sum over its nodes. ``materials`` is the list of
:class:`reflab.reconstruction.scene.Material` in surface order (``[s.material for s in scene]``);
``intensities`` is ``lights.intensities`` (K, 3).
"""
from __future__ import annotations

import threading
from collections import Counter

import numpy as np

from reflab.inverse.forward.models import MAX_LINEAR, MAX_NONLINEAR, get_model
from reflab.inverse.forward.trees import derived


def _check(trees, materials, intensities=None):
    if len(trees) and int(trees.surface.max()) >= len(materials):
        raise ValueError(f"the trees reference surface {int(trees.surface.max())} but only {len(materials)} materials were given")
    if intensities is None:
        return None
    intensities = np.asarray(intensities, dtype=np.float64)
    if intensities.shape != (trees.n_lights, 3) or not np.all(np.isfinite(intensities)):
        raise ValueError(f"intensities: expected finite values of shape ({trees.n_lights}, 3), got {intensities.shape}")
    return intensities


def _groups(trees) -> list:
    """(surface index, node indices) for each surface that has nodes (sorted once per trees)."""
    def groups():
        order = np.argsort(trees.surface, kind="stable")
        count = np.bincount(trees.surface) if len(trees.surface) else np.zeros(0, dtype=np.int64)
        parts = np.split(order, np.cumsum(count)[:-1])  # np.unique's hashing took 0.2 s a 0.5 MP tile
        return [(s, part) for s, part in enumerate(parts) if len(part)]

    return derived(trees, "surface groups", (trees.surface,), groups)


def surface_parameters(materials, surfaces) -> tuple[np.ndarray, np.ndarray]:
    """Linear parameters ``x`` (S, 3, L) and nonlinear ``θ`` (S, P) of the surfaces ``surfaces``
    (indices; the other rows 0), zero-padded as :func:`node_parameters` gives them per node."""
    x = np.zeros((len(materials), 3, MAX_LINEAR))
    theta = np.zeros((len(materials), MAX_NONLINEAR))
    for s in surfaces:
        model = get_model(materials[s].brdf)
        x[s, :, : model.n_linear] = model.x_of(materials[s])
        theta[s, : model.n_nonlinear] = model.theta_of(materials[s])
    return x, theta


def node_parameters(trees, materials, nodes=None) -> tuple[np.ndarray, np.ndarray]:
    """Linear parameters ``x`` (N, 3, L) and nonlinear ``θ`` (N, P) of each node's surface (of the
    nodes ``nodes`` only, if given).

    ``L`` and ``P`` are the largest counts over all models; unused slots are 0. ``kd`` is slot 0
    of every model.
    """
    _check(trees, materials)
    # One row per surface, gathered by node: the same numbers as filling each surface's nodes (a
    # fit asks a dozen times for 300 000 nodes' worth).
    x, theta = surface_parameters(materials, [s for s, _ in _groups(trees)])
    surface = np.asarray(trees.surface if nodes is None else trees.surface[nodes], dtype=np.int64)
    return x[surface], theta[surface]


def linear_basis_and_grad(trees, materials, intensities, *, grad: bool = True):
    """Coefficients of each node's linear parameters, and their derivative in its θ.

    Parameters
    ----------
    trees : reflab.inverse.forward.trees.Trees
    materials : list of Material
        The nonlinear parameters (and model) of each surface are read here.
    intensities : (K, 3) array_like
    grad : bool
        Also compute the derivative (else None is returned for it).

    Returns
    -------
    basis : (N, 3, L) ndarray
        ``fresnel · Σ_k visible · intensity_k[c] / dist2 · g_j``, zero-padded to L.
    dbasis : (N, 3, L, P) ndarray or None
        d basis / d θ_p of the node's surface, zero-padded to P.
    """
    intensities = _check(trees, materials, intensities)
    n = len(trees)
    basis = np.zeros((n, 3, MAX_LINEAR))
    dbasis = np.zeros((n, 3, MAX_LINEAR, MAX_NONLINEAR)) if grad else None
    for s, idx in _groups(trees):
        _surface_basis(trees, materials[s], idx, intensities, basis, dbasis)
    return basis, dbasis


def node_geometry(trees, idx) -> tuple:
    """Normals, light directions and views per (node, light) of the nodes ``idx`` (n·K, 3), and
    their known weights ``fresnel · visible / dist²`` (n, K): what a model needs at those nodes
    (:func:`model_geometry` turns them into :func:`basis_on`'s input)."""
    k = trees.n_lights
    return (np.repeat(trees.normal[idx], k, axis=0), trees.light_dir[idx].reshape(-1, 3),
            np.repeat(trees.view[idx], k, axis=0), trees.fresnel[idx, None] * trees.visible[idx] / trees.light_dist2[idx])


def model_geometry(model, geometry) -> tuple:
    """(``model``'s θ-independent terms, weights) from a :func:`node_geometry` tuple: what
    :func:`basis_on` needs, formed once for the many θ a few nodes are evaluated at (the half
    vector, its logarithm: most of a model's cost)."""
    normal, light, view, weight = geometry
    return model.geometry(normal, light, view), weight


def basis_on(model, theta, geometry, intensities) -> np.ndarray:
    """(n, 3, L) coefficients of ``model``'s linear parameters at nonlinear parameters ``theta``
    (P,) on nodes of :func:`model_geometry` (a few nodes at many θ: :mod:`reflab.inverse.fit.dichromatic`)."""
    terms, weight = geometry
    g = model.g_and_dg_on(np.asarray(theta, dtype=np.float64), terms, grad=False)[0]
    return _weighted(weight, intensities, g)


def _weighted(weight, intensities, g) -> np.ndarray:
    """``Σ_k weight · intensity_k[c] · g`` per node: (n, 3, L) from g per (node, light) (n·K, L)."""
    n, k = weight.shape
    # One (3 x K)(K x L) product per node, batched: 10x faster than einsum's pairwise contraction
    # ("nk,kc,nkl->ncl", optimize=True), which was a sixth of a 12 MP texture's time.
    wc = weight[:, :, None] * np.asarray(intensities, dtype=np.float64)[None]  # (n, K, 3)
    return np.matmul(wc.transpose(0, 2, 1), g.reshape(n, k, -1))


def _surface_weight(trees, idx) -> np.ndarray:
    """:func:`node_geometry`'s weights ``fresnel · visible / dist²`` (n, K) of one surface's nodes
    ``idx``, kept on the trees (a fit's texture rounds evaluate the same surfaces again at other θ).
    The weights alone: the basis reads nothing else of the geometry (the repeated normals and
    views were two (n·K, 3) copies a surface, kept on the trees with the weights)."""
    # idx: one of _groups' arrays, kept with the trees.
    return derived(trees, f"surface weight {id(idx)}", (trees.fresnel, trees.visible, trees.light_dist2, idx),
                   lambda: trees.fresnel[idx, None] * trees.visible[idx] / trees.light_dist2[idx])


def _surface_terms(trees, model, idx) -> tuple:
    """``model``'s θ-independent terms (:meth:`Model.geometry`) on one surface's (node, light)
    pairs, kept on the trees like :func:`_surface_weight`: each new θ of the surface then costs
    its lobe alone (640x480 zoo scene: the half vectors' norms and logarithms were a sixth of a
    fit's texture rounds, recomputed at every θ). The same numbers as the model on (n, l, v)."""
    def terms():
        k = np.shape(trees.light_dir)[1]  # node_geometry's (n, l, v), without its weights
        return model.geometry(np.repeat(trees.normal[idx], k, axis=0), trees.light_dir[idx].reshape(-1, 3),
                              np.repeat(trees.view[idx], k, axis=0))

    return derived(trees, f"surface terms {model.name} {id(idx)}", (trees.normal, idx), terms)


def surface_terms(trees, model, s: int) -> tuple[tuple, np.ndarray]:
    """``model``'s θ-independent terms on the (node, light) pairs of surface ``s`` (rows node-major,
    :func:`node_geometry`'s order) and the surface's nodes, increasing: kept on the trees, so that
    the factorizations of one fit (its sample, coarse scan, outliers left out, texture rounds)
    take theirs from one computation (:meth:`reflab.inverse.forward.factorization.Factorization`)."""
    idx = next((part for t, part in _groups(trees) if t == s), np.zeros(0, dtype=np.int64))
    return _surface_terms(trees, model, idx), idx


def _surface_basis(trees, material, idx, intensities, basis, dbasis=None) -> None:
    """Fill ``basis`` (and ``dbasis``) at the nodes ``idx`` of one surface, whose material is ``material``."""
    k = trees.n_lights
    model = get_model(material.brdf)
    weight = _surface_weight(trees, idx)
    g, dg = model.g_and_dg_on(model.theta_of(material), _surface_terms(trees, model, idx), grad=dbasis is not None)
    L, P = model.n_linear, model.n_nonlinear
    if dbasis is not None:
        dbasis[idx, :, :L, :P] = np.einsum("nk,kc,nklp->nclp", weight, intensities, dg.reshape(len(idx), k, L, P),
                                           optimize=True)
    basis[idx, :, :L] = _weighted(weight, intensities, g)


#: The last :func:`linear_basis` of each thread as one (trees, key, basis) tuple (``.value``,
#: read and replaced whole): a texture round asks for the same one up to three times (direct
#: share, texture system, texture test), 60 ms each at 640×480; the next asks for one where only
#: a few small surfaces' θ moved (a matte ground, a mirror, a pane keep theirs). Per thread: a
#: tiled texture reduces two tiles at once, each asking for its own tile's basis three times.
_LAST_BASIS = threading.local()


def linear_basis(trees, materials, intensities) -> np.ndarray:
    """(N, 3, L) coefficients of each node's linear parameters (see :func:`linear_basis_and_grad`).

    Read-only: the last one is kept and handed out again for the same trees, models, θ and
    intensities (the only inputs it depends on); from it, only the surfaces whose model or θ
    changed are computed again.
    """
    _check(trees, materials)
    surfaces = tuple((m.brdf, get_model(m.brdf).theta_of(m).tobytes()) for m in materials)
    key = (surfaces, np.asarray(intensities, dtype=np.float64).tobytes())
    last = getattr(_LAST_BASIS, "value", None)
    if last is not None and last[0] is trees and last[1] == key:
        return last[2]
    if last is not None and last[0] is trees and last[1][1] == key[1] and len(last[1][0]) == len(surfaces):
        basis = last[2].copy()
        intensities = _check(trees, materials, intensities)
        for s, idx in _groups(trees):
            if last[1][0][s] != surfaces[s]:
                basis[idx] = 0.0  # another model may fill fewer slots
                _surface_basis(trees, materials[s], idx, intensities, basis)
    else:
        basis = linear_basis_and_grad(trees, materials, intensities, grad=False)[0]
    basis.flags.writeable = False
    _LAST_BASIS.value = (trees, key, basis)
    return basis


def release_basis() -> None:
    """Forget the basis :func:`linear_basis` keeps in this thread, and with it the trees it was
    computed for (a tiled stage's last tile: about 1 GB that would otherwise outlive the tile)."""
    _LAST_BASIS.value = None


def path_products(trees, materials, *, per_path: bool = False) -> np.ndarray:
    """(N, 3) product of ``r_s`` (reflection) and ``t_s`` (transmission) along each node's path;
    with ``per_path``, (len(trees.paths), 3) per distinct path (index it with ``trees.path``)."""
    _check(trees, materials)
    products = np.ones((len(trees.paths), 3))
    for i, path in enumerate(trees.paths):  # one iteration per distinct path, not per node
        for s, kind in path:
            products[i] *= np.asarray(materials[s]["t" if kind else "r"], dtype=np.float64)
    return products if per_path else products[trees.path]


def accumulate(trees, values: np.ndarray) -> np.ndarray:
    """Sum per-node values (N, 3) into an (H, W, 3) float64 image by pixel."""
    size = trees.width * trees.height
    img = np.stack([np.bincount(trees.pixel, weights=values[:, c], minlength=size) for c in range(3)], axis=1)
    return img.reshape(trees.height, trees.width, 3)


def node_radiance(trees, materials, intensities, *, kd_nodes=None, basis=None) -> np.ndarray:
    """(N, 3) contribution of each node to its pixel: path product · basis · x.

    Parameters
    ----------
    kd_nodes : (N, 3) array_like, optional
        Per-node diffuse albedo replacing the surface's ``kd`` (texture stage).
    basis : (N, 3, L) ndarray, optional
        A precomputed :func:`linear_basis` for these materials' nonlinear parameters, to skip
        evaluating the models when only linear parameters, r or t changed.
    """
    x, _ = node_parameters(trees, materials)
    if kd_nodes is not None:
        kd_nodes = np.asarray(kd_nodes, dtype=np.float64)
        if kd_nodes.shape != (len(trees), 3):
            raise ValueError(f"kd_nodes: expected shape ({len(trees)}, 3), got {kd_nodes.shape}")
        x[:, :, 0] = kd_nodes
    if basis is None:
        basis = linear_basis(trees, materials, intensities)
    elif basis.shape != x.shape:
        raise ValueError(f"basis: expected shape {x.shape}, got {basis.shape}")
    return path_products(trees, materials) * np.einsum("ncl,ncl->nc", basis, x)


def render(trees, materials, intensities, *, kd_nodes=None, basis=None) -> np.ndarray:
    """The (H, W, 3) float64 linear image predicted by the trees for these parameters."""
    return accumulate(trees, node_radiance(trees, materials, intensities, kd_nodes=kd_nodes, basis=basis))


def render_albedo(trees, materials, kd_nodes=None) -> np.ndarray:
    """(H, W, 3) ``kd`` of the surface seen directly at each pixel; NaN where it sees nothing."""
    x, _ = node_parameters(trees, materials)
    kd = x[:, :, 0] if kd_nodes is None else np.asarray(kd_nodes, dtype=np.float64)
    out = np.full((trees.width * trees.height, 3), np.nan)
    primary = trees.level == 1
    out[trees.pixel[primary]] = kd[primary]
    return out.reshape(trees.height, trees.width, 3)


# ---------------------------------------------------------------------- what a prediction rests on
#: A pixel whose predicted light rests for more than this share (in some band) on parameters the
#: image did not determine is itself undetermined: its value is a guess (docs/fit.md, "Renders that
#: say where they guess").
UNDETERMINED_SHARE = 0.05
#: ... unless that part is below this fraction of the image's peak (dark pixels, faint tails).
UNDETERMINED_FLOOR = 1e-3
#: Where the photograph's noise σ is known, a part above this many σ (at the view's peak) is
#: undetermined whatever its share: a guess that moves the pixel by more than the photograph pins
#: anything down is not determined (noise-free, every visible trace of a guessed lobe counts).
UNDETERMINED_NOISE = 2.0


def _named_bands(names) -> dict:
    """fit.json names ("ks", "r[2]") as {name: (3,) bool bands}."""
    out = {}
    for name in names:
        base, _, band = name.partition("[")
        mask = out.setdefault(base, np.zeros(3, dtype=bool))
        if band:
            mask[int(band.rstrip("]"))] = True
        else:
            mask[:] = True
    return out


def undetermined_radiance(trees, materials, intensities, undetermined, *, kd_nodes=None, textured=None,
                          guessed=None) -> np.ndarray:
    """(N, 3) part of each node's radiance that rests on parameters the image did not determine.

    Parameters
    ----------
    undetermined : list of iterable of str
        Per surface, parameter names as fit.json's ``undetermined`` gives them (``"ks"``,
        ``"r[2]"``, ``"ns"``), less what the user gave (a given value is known, not undetermined).
    kd_nodes : (N, 3) array_like, optional
        Per-node albedo (the texture), as for :func:`node_radiance`.
    textured : sequence of bool, optional
        Per surface: its kd is the texture's, judged by the texture stage, not by fit.json.
    guessed : (N,) bool, optional
        Nodes whose albedo is a guess (texels the texture stage flagged: made from pixels whose
        light rested on undetermined parameters): their diffuse term counts as undetermined.

    A linear term is undetermined when its parameter is, or when it is shaped by an undetermined
    θ (:attr:`reflab.inverse.forward.models.Model.shaped`: a Phong lobe whose ns is free); a whole node when its
    path passes a reflection or transmission coefficient that is undetermined.
    """
    intensities = _check(trees, materials, intensities)
    n_s = len(materials)
    slots = np.zeros((n_s, 3, MAX_LINEAR), dtype=bool)
    coeff = np.zeros((n_s, 2, 3), dtype=bool)  # r, t bands
    for s in range(n_s):
        model = get_model(materials[s].brdf)
        names = _named_bands(undetermined[s] if s < len(undetermined) else ())
        for j, name in enumerate(model.linear):
            if name in names and not (j == 0 and textured is not None and textured[s]):
                slots[s, :, j] |= names[name]
        if any(p in names for p in model.nonlinear):
            slots[s, :, list(model.shaped)] = True
        coeff[s] = [names.get("r", np.zeros(3, bool)), names.get("t", np.zeros(3, bool))]
    per_path = np.zeros((len(trees.paths), 3), dtype=bool)
    for i, path in enumerate(trees.paths):  # one iteration per distinct path
        for s, kind in path:
            per_path[i] |= coeff[s, int(bool(kind))]
    # Only the nodes on which something is undetermined (a tiled texture: most nodes are a
    # textured ground's, whose part is exactly 0); the others keep 0, as they would in full.
    some = slots.any(axis=(1, 2))[trees.surface] | per_path.any(axis=1)[trees.path]
    if guessed is not None:
        guessed = np.asarray(guessed, dtype=bool)
        some |= guessed
    sel = np.flatnonzero(some)
    del some
    out = np.zeros((len(trees), 3))
    if len(sel) == 0:
        return out
    x, _ = node_parameters(trees, materials, sel)  # the selected nodes' only
    if kd_nodes is not None:
        x[:, :, 0] = np.asarray(kd_nodes, dtype=np.float64)[sel]
    path_sel = trees.path[sel]
    terms = linear_basis(trees, materials, intensities)[sel] * x * path_products(trees, materials, per_path=True)[path_sel][:, :, None]
    del x
    slot = slots[trees.surface[sel]]
    if guessed is not None:
        slot[:, :, 0] |= guessed[sel][:, None]
    part = np.where(slot, terms, 0.0).sum(axis=2)
    out[sel] = np.where(per_path[path_sel], terms.sum(axis=2), part)
    return out


def uncertain_radiance(trees, materials, intensities, sigma, *, kd_nodes=None, textured=None) -> np.ndarray:
    """(N, 3) one-sigma of each node's radiance from the σ of the parameters the fit determined.

    Parameters
    ----------
    sigma : list of dict
        Per surface, fit.json's ``sigma``: name -> (3,) per band or a float for θ; None (or a
        missing name) where the fit holds or calls the value undetermined (those are
        :func:`undetermined_radiance`'s) or the user gave it.
    kd_nodes, textured
        As for :func:`undetermined_radiance`; a textured surface's kd is the texture's (judged by
        the texture stage), so its σ is not counted.

    Each parameter's part is its derivative times its σ, linearised; the parts add in quadrature
    at a node (as if independent). A reflection or transmission coefficient that is exactly 0 in
    every band has no branch in the trees, so its σ shows nowhere.
    """
    intensities = _check(trees, materials, intensities)
    n_s = len(materials)

    def params(nodes):
        """x (n, 3, L) of the nodes ``nodes`` only (most of a tiled texture's have no σ)."""
        x = node_parameters(trees, materials, nodes)[0]
        if kd_nodes is not None:
            x[:, :, 0] = np.asarray(kd_nodes, dtype=np.float64)[nodes]
        return x

    def sig(s, name, n):
        """σ of ``name`` on surface s as n floats: 0 where fit.json gives none (null or missing)."""
        v = sigma[s].get(name) if s < len(sigma) and sigma[s] else None
        v = [0.0 if e is None else float(e) for e in (v if isinstance(v, list) else [v] * n)]
        return np.nan_to_num(np.asarray(v, dtype=np.float64), nan=0.0, posinf=0.0)

    sx = np.zeros((n_s, 3, MAX_LINEAR))
    st = np.zeros((n_s, MAX_NONLINEAR))
    sf = np.zeros((n_s, 2, 3))  # r, t
    for s in range(n_s):
        model = get_model(materials[s].brdf)
        for j, name in enumerate(model.linear):
            if not (j == 0 and textured is not None and textured[s]):
                sx[s, :, j] = sig(s, name, 3)
        for j, name in enumerate(model.nonlinear):
            st[s, j] = sig(s, name, 1)[0]
        sf[s] = [sig(s, "r", 3), sig(s, "t", 3)]
    basis = linear_basis(trees, materials, intensities)  # the kept one: a tiled texture's tile asked for it already
    prod = path_products(trees, materials, per_path=True)  # per distinct path
    # d(path product)/d(factor) · σ, one distinct path at a time: the product of the path's other
    # factors times the factor's exponent and power below (a zero factor's branch still counts).
    dpath = np.zeros((len(trees.paths), 3))
    for i, path in enumerate(trees.paths):
        count = Counter((s, int(bool(kind))) for s, kind in path)
        for (s, kind), e in count.items():
            others = np.ones(3)
            for (s2, k2), e2 in count.items():
                if (s2, k2) != (s, kind):
                    others *= np.asarray(materials[s2]["t" if k2 else "r"], dtype=np.float64) ** e2
            value = np.asarray(materials[s]["t" if kind else "r"], dtype=np.float64)
            dpath[i] += (e * value ** (e - 1) * others * sf[s, kind]) ** 2
    # Only the nodes with some σ (a tiled texture: most nodes are a textured ground's, whose kd's
    # σ is the texture's and whose variance is exactly 0); the others keep 0, as they would in full.
    sel = np.flatnonzero((sx.any(axis=(1, 2)) | st.any(axis=1))[trees.surface] | dpath.any(axis=1)[trees.path])
    var = np.zeros((len(trees), 3))
    if len(sel) == 0:
        return var
    surf_sel, path_sel = trees.surface[sel], trees.path[sel]
    var[sel] = ((basis[sel] * sx[surf_sel]) ** 2).sum(axis=2) * prod[path_sel] ** 2
    # θ's part on the surfaces whose θ has a σ only (a 12 MP texture: the derivatives of every
    # node took a sixth of its time, most of them on a Lambertian ground with no θ).
    for s, idx in _groups(trees):
        if not st[s].any():
            continue
        model = get_model(materials[s].brdf)
        L, P, k = model.n_linear, model.n_nonlinear, trees.n_lights
        weight = _surface_weight(trees, idx)
        _, dg = model.g_and_dg_on(model.theta_of(materials[s]), _surface_terms(trees, model, idx))
        dbasis = _weighted(weight, intensities, dg.reshape(len(idx) * k, L * P)).reshape(len(idx), 3, L, P)
        dtheta = np.einsum("nclp,ncl->ncp", dbasis, params(idx)[:, :, :L]) * st[s, :P]
        var[idx] += (dtheta**2).sum(axis=2) * prod[trees.path[idx]] ** 2
    var[sel] += np.einsum("ncl,ncl->nc", basis[sel], params(sel)) ** 2 * dpath[path_sel]
    return np.sqrt(var)


def undetermined_pixels(trees, materials, intensities, undetermined, *, kd_nodes=None, textured=None, guessed=None,
                        image=None, sigma=None, noise=None, share: float = UNDETERMINED_SHARE,
                        floor: float = UNDETERMINED_FLOOR) -> np.ndarray:
    """(H, W) bool: pixels whose predicted light rests for more than ``share`` of it on undetermined
    parameters (and for more than ``floor`` of the peak); see :func:`undetermined_radiance`.

    ``noise`` (3,), optional: the photograph's noise σ per band as a fraction of its peak
    (:class:`reflab.inverse.texture.solve.Uncertainty`): a part above :data:`UNDETERMINED_NOISE` times it (at
    this view's peak) is undetermined too, however small its share.

    ``image`` (H, W, 3), optional: the photograph to measure the share against (the texture stage,
    before any texture is known); default the prediction itself. ``sigma`` (fit.json's, per
    surface), optional: the one-sigma the determined parameters give the pixel
    (:func:`uncertain_radiance`) counts too, so that a value known only to ±60 % (a faint
    reflection) does not pass for determined.
    """
    part = undetermined_part(trees, materials, intensities, undetermined, kd_nodes=kd_nodes, textured=textured,
                             guessed=guessed, sigma=sigma)
    if image is None:
        total = render(trees, materials, intensities, kd_nodes=kd_nodes)
    else:
        total = np.asarray(image, dtype=np.float64).reshape(part.shape)
    peak = float(total.max()) if total.size else 0.0
    return undetermined_decision(part, total, peak, noise=noise, share=share, floor=floor)


def undetermined_part(trees, materials, intensities, undetermined, *, kd_nodes=None, textured=None, guessed=None,
                      sigma=None) -> np.ndarray:
    """(H, W, 3) the light of each pixel that rests on undetermined parameters, plus the one-sigma
    of the determined ones when ``sigma`` is given: :func:`undetermined_pixels`' measure, pixel by
    pixel (a tile of pixels at a time gives the same values)."""
    part = accumulate(trees, np.abs(undetermined_radiance(trees, materials, intensities, undetermined,
                                                          kd_nodes=kd_nodes, textured=textured, guessed=guessed)))
    if sigma is not None and any(sigma):
        part = part + accumulate(trees, uncertain_radiance(trees, materials, intensities, sigma, kd_nodes=kd_nodes,
                                                           textured=textured))
    return part


def undetermined_decision(part, total, peak: float, *, noise=None, share: float = UNDETERMINED_SHARE,
                          floor: float = UNDETERMINED_FLOOR) -> np.ndarray:
    """(…) bool: where :func:`undetermined_part`'s ``part`` (…, 3) exceeds its limit against the
    pixels' ``total`` (…, 3) and the whole view's ``peak`` (see :func:`undetermined_pixels`)."""
    limit = np.maximum(share * np.abs(total), floor * peak)
    if noise is not None:
        limit = np.minimum(limit, UNDETERMINED_NOISE * np.asarray(noise, dtype=np.float64) * peak)
    return np.any(part > limit, axis=-1)
