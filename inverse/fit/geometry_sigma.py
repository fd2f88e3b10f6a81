"""The reconstructed geometry's uncertainty propagated into every fitted value's σ.

The fit's σ (:mod:`reflab.inverse.fit.uncertainty`) knows the photographs' noise and misfit, not
that the meshes it models them with are themselves measured: the demo's transparent sheet, its
mesh from marked corners 1.5 mrad and 0.2 mm off the truth, fitted ks 0.182 ± 0.004 for a true
0.20 (docs/fit.md). scene.json may give each surface a ``pose_sigma`` (docs/formats.md, written by
``reflab reconstruct``): the one-sigma tilt about two axes in its plane and offset along its normal.
Each of those three pose changes g moves the model's pixels by ∂m/∂g (finite differences: the
trees of the rows that see the surface rebuilt with its mesh moved by ±σ_g), which moves the fitted
values by dθ/dg = −H⁻¹ JᵀW ∂m/∂g; ``Cov_θ += Σ_g (dθ/dg) σ_g² (dθ/dg)ᵀ``. A surface without
``pose_sigma`` (a user's own mesh, the simulated zoo's exact geometry) adds nothing.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

#: scene.json's per-surface field (docs/formats.md).
FIELD = "pose_sigma"
#: The pixels rebuilt: those whose trees meet the moved surface and this many around them (a
#: moved edge may cover a pixel that did not see it).
EDGE_PAD = 2


@dataclasses.dataclass(frozen=True)
class PoseSigma:
    """A plane's pose uncertainty: tilts about ``axes`` through ``centre``, offset along ``normal``."""

    centre: np.ndarray
    normal: np.ndarray
    axes: np.ndarray  # (2, 3) unit vectors in the plane
    tilt_rad: np.ndarray  # (2,) one-sigma tilt about each axis
    offset_m: float  # one-sigma offset along the normal
    shift_m: np.ndarray | None = None  # (2,) one-sigma shift along each axis (where a bounded face's edges lie)

    def to_json(self, source: str = "") -> dict:
        out = {"centre": [float(v) for v in self.centre], "normal": [float(v) for v in self.normal],
               "axes": [[float(v) for v in a] for a in self.axes],
               "tilt_rad": [float(v) for v in self.tilt_rad], "offset_m": float(self.offset_m)}
        if self.shift_m is not None:
            out["shift_m"] = [float(v) for v in self.shift_m]
        if source:
            out["from"] = source
        return out

    @classmethod
    def from_json(cls, obj, path="scene.json", where: str = FIELD) -> "PoseSigma":
        """Parse scene.json's ``pose_sigma``; WorkspaceError naming the bad field."""
        from reflab.core.workspace import WorkspaceError

        if not isinstance(obj, dict):
            raise WorkspaceError(path, where, "an object with centre, normal, axes, tilt_rad, offset_m", got=obj)

        def arr(key, shape):
            try:
                a = np.asarray(obj.get(key), dtype=np.float64).reshape(shape)
            except (TypeError, ValueError):
                raise WorkspaceError(path, f"{where}.{key}", f"{int(np.prod(shape))} numbers", got=obj.get(key)) from None
            if not np.all(np.isfinite(a)):
                raise WorkspaceError(path, f"{where}.{key}", "finite numbers", got=obj.get(key))
            return a

        tilt, offset = arr("tilt_rad", (2,)), float(arr("offset_m", (1,))[0])
        if np.any(tilt < 0) or offset < 0:
            raise WorkspaceError(path, where, "tilt_rad and offset_m >= 0 (one-sigma values)",
                                 got={"tilt_rad": obj.get("tilt_rad"), "offset_m": obj.get("offset_m")})
        shift = None if obj.get("shift_m") is None else arr("shift_m", (2,))
        if shift is not None and np.any(shift < 0):
            raise WorkspaceError(path, f"{where}.shift_m", "two one-sigma values >= 0", got=obj.get("shift_m"))
        normal, axes = arr("normal", (3,)), arr("axes", (2, 3))
        unit = lambda v: v / max(np.linalg.norm(v), 1e-300)  # noqa: E731
        return cls(arr("centre", (3,)), unit(normal), np.stack([unit(a) for a in axes]), tilt, offset, shift)

    def moves(self) -> list[tuple[str, float, np.ndarray, np.ndarray]]:
        """Each pose change of nonzero σ: ``(name, σ, rotation vector per unit, translation per unit)``."""
        out = [(f"tilt{k}", float(self.tilt_rad[k]), self.axes[k], np.zeros(3)) for k in range(2)]
        out.append(("offset", float(self.offset_m), np.zeros(3), self.normal))
        if self.shift_m is not None:
            out += [(f"shift{k}", float(self.shift_m[k]), np.zeros(3), self.axes[k]) for k in range(2)]
        return [m for m in out if m[1] > 0]


def pose_sigma(surface, path="scene.json") -> PoseSigma | None:
    """The surface's ``pose_sigma`` from scene.json, or None when it has none."""
    obj = surface.extra.get(FIELD) if surface.extra else None
    return None if obj is None else PoseSigma.from_json(obj, path, f"{surface.name}.{FIELD}")


def moved_scene(scene, index: int, pose: PoseSigma, rvec, shift):
    """A copy of ``scene`` with surface ``index``'s mesh turned by ``rvec`` about the pose's centre and shifted."""
    from reflab.calibration.rotations import rodrigues
    from reflab.reconstruction.scene import Mesh, Scene

    R = rodrigues(np.asarray(rvec, dtype=np.float64))
    s = scene.surfaces[index]
    m = s.mesh
    verts = (m.vertices - pose.centre) @ R.T + pose.centre + shift
    mesh = Mesh(verts, m.triangles, None if m.normals is None else m.normals @ R.T)
    surfaces = list(scene.surfaces)
    surfaces[index] = dataclasses.replace(s, mesh=mesh)
    return Scene(surfaces, scene.root)


def _solve(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``H⁻¹ g`` on the constrained directions (diagonal scaling, eigenvalues floored as σ's are)."""
    out = np.zeros_like(g)
    dg = np.sqrt(np.maximum(np.diag(H), 0.0))
    ok = dg > 0
    if not ok.any():
        return out
    w, V = np.linalg.eigh(H[np.ix_(ok, ok)] / np.outer(dg[ok], dg[ok]))
    w = np.maximum(w, 1e-14 * max(w.max(), 1e-300))
    out[ok] = ((V / w) @ (V.T @ (g[ok] / dg[ok]))) / dg[ok]
    return out


def propagate(stack, photos, scene, depth: int, fac, image, result, *, task=None):
    """The variance the surfaces' pose uncertainty adds to each fitted value.

    Parameters
    ----------
    stack, photos
        The fitted photographs' stacked trees and the photographs
        (:func:`reflab.inverse.fit.photograph.stack_photographs`).
    scene : reflab.reconstruction.scene.Scene
    depth : int
        The trees' depth.
    fac : Factorization
        The system the fit was judged on (its ``rows`` the pixels read).
    image : (H, W, 3) ndarray
        The stacked photograph.
    result : FitSolution

    Returns
    -------
    var : Params or None
        Added variance per parameter (0 where nothing moves it); None when no surface that the
        used pixels see has a ``pose_sigma``.
    report : dict
        Per surface: its pose σ, the pixels it moves and the seconds spent; ``time_s`` in all.
    """
    from scipy.ndimage import binary_dilation

    from reflab.core.task import ensure
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees
    from reflab.inverse.fit.diagnosis import REJECT_SHARE, outlier_tolerance
    from reflab.inverse.fit.problem import Params, Problem
    from reflab.inverse.fit.uncertainty import normal_matrix, row_jacobian, scatter

    t0 = time.perf_counter()
    task = ensure(task)
    trees = stack.trees
    poses = {i: pose_sigma(s) for i, s in enumerate(scene)}
    poses = {i: p for i, p in poses.items() if p is not None and p.moves()}
    report = {}
    if not poses or fac.n_rows == 0:
        return None, {"surfaces": report, "time_s": round(time.perf_counter() - t0, 6)}
    pb = Problem(fac, image, [m.transparent for m in result.materials])
    noise = np.maximum(np.asarray(result.stats.get("noise") or pb.noise, dtype=np.float64), 1e-300)
    weights = 1.0 / noise ** 2
    rows = np.asarray(fac.rows, dtype=np.int64)
    at = np.full(trees.width * trees.height, -1, dtype=np.int64)
    at[rows] = np.arange(len(rows))
    scale = getattr(pb, "scale", None)
    H = tol = None
    xy = np.asarray(result.stats.get("rejected", {}).get("pixels") or np.zeros((0, 2)), dtype=np.int64).reshape(-1, 2)
    rejected = xy[:, 1] * trees.width + xy[:, 0]
    acc = None
    for index, pose in poses.items():
        ts = time.perf_counter()
        # The used pixels whose trees meet the surface, and their neighbours (a moved edge covers them).
        near = np.zeros((trees.height, trees.width), dtype=bool)
        near.flat[np.asarray(trees.pixel)[np.asarray(trees.surface) == index]] = True
        near = binary_dilation(near, iterations=EDGE_PAD).reshape(-1)
        px = np.flatnonzero(near & (at >= 0))
        if len(px) == 0:
            continue
        which = stack.photograph_of(px)
        moves = pose.moves()
        dms = np.zeros((len(moves), 3, len(px)))
        for i in np.unique(which):
            block, photo = stack.blocks[i], photos[i]
            sel = which == i
            v, u = np.divmod(px[sel], trees.width)
            v = v - block.row0
            r0, r1 = int(v.min()), int(v.max()) + 1
            at_px = (v - r0) * block.width + u

            def model(sc):
                task.check()
                part = build_trees(sc, photo.camera, photo.lights, depth, rows=(r0, r1), pixels=at_px)
                return render(part, result.materials, photo.lights.intensities).reshape(-1, 3)[at_px]

            # At full resolution: a moved edge flips whole pixels, each with its own Jacobian
            # (the sheet's parameters act on one side only); binned 2x2 it lost half the sheet's
            # blue ks term. One side, a whole σ away: the secant over the pose's likely range.
            base = model(scene)
            for k, (_, sd, rvec, shift) in enumerate(moves):
                dms[k][:, sel] = (model(moved_scene(scene, index, pose, sd * rvec, sd * shift)) - base).T
        # A pixel the moved pose makes an outlier (a moved edge flips what it sees) is one the fit
        # leaves out (diagnosis.outliers): it moves nothing. Counted, 37 such pixels of a sheet
        # offset 0.1 mm at 160x120 made its ns ± 70 (a 3 mrad tilt moved its fit by 1).
        if tol is None:
            A = fac.matrices(result.params.theta)
            A, res = pb.unweighted(A, pb.residual(A, fac.y(result.params.x, result.params.s)))
            tol = outlier_tolerance(pb, result.params, A, res, [s.textured for s in scene])
        r0_, t0_ = res[:, at[px]], tol[:, at[px]]
        out = np.isin(px, rejected)  # left out of the fit already
        dms[:, :, out] = 0.0
        for k in range(len(moves)):
            flipped = np.any(np.abs(r0_ + dms[k]) > t0_, axis=0) & ~out
            if flipped.sum() <= REJECT_SHARE * fac.n_rows:
                dms[k][:, flipped] = 0.0
        if H is None:
            H, labels = normal_matrix(pb, result.params, result.free, weights)
        # JᵀW ∂m/∂g over the surface's pixels only (dm is 0 elsewhere).
        J = row_jacobian(pb, result.params, result.free, at[px])  # (3, m, n)
        if scale is not None:
            dms = dms * scale[at[px]]
        g = np.einsum("c,cmn,kcm->kn", weights, J, dms)
        del J
        deltas = [-_solve(H, gk) for gk in g]
        d = np.array(deltas)
        acc = (d ** 2).sum(axis=0) if acc is None else acc + (d ** 2).sum(axis=0)
        report[scene.names[index]] = {"pose_sigma": pose.to_json(), "pixels": int(len(px)),
                                      "time_s": round(time.perf_counter() - ts, 6)}
    if acc is None:
        return None, {"surfaces": report, "time_s": round(time.perf_counter() - t0, 6)}
    p = result.params
    var = scatter(labels, acc, Params(np.zeros_like(p.x), np.zeros_like(p.s), np.zeros_like(p.theta)))
    return var, {"surfaces": report, "time_s": round(time.perf_counter() - t0, 6)}


def widened(result, fac, image, scene, var):
    """``result`` with ``var`` added to its σ² and what the wider σ leaves loose reported undetermined.

    Judged as the fit judges its own σ (:func:`reflab.inverse.fit.determined.unresolved`, a lobe's
    height and width together); a value the geometry makes loose keeps its fitted value, reported
    undetermined. fit.json's ``geometry_sigma`` keeps the σ without the geometry's share.
    """
    from reflab.inverse.fit.determined import RESOLVE_LOBE, RESOLVE_THETA, undetermined_names, unresolved
    from reflab.inverse.fit.problem import Free, Params, Problem, params_of

    old = result.sigma
    sig = Params(*(np.where(np.isfinite(o), np.sqrt(o ** 2 + v), o) for o, v in
                   ((old.x, var.x), (old.s, var.s), (old.theta, var.theta))))
    pb = Problem(fac, image, [m.transparent for m in result.materials])
    init = params_of(fac, [s.material for s in scene])
    init.theta = pb.search.to_theta(pb.search.to_u(init.theta))
    A = fac.matrices(result.params.theta)
    free = result.free

    def judged(s):
        return unresolved(pb, result.params, init, free, s, A, theta_resolve=RESOLVE_THETA, bounds_hold=False,
                          lobe_resolve=RESOLVE_LOBE)

    was, now = judged(old), judged(sig)
    loose = Free(now.x & ~was.x, now.s & ~was.s, now.theta & ~was.theta)
    lay = fac.layout
    for s, model in enumerate(fac.models):  # a lobe's height and width stand or fall together
        th = slice(lay.theta_offset[s], lay.theta_offset[s + 1])
        lobe = [lay.x_offset[s] + j for j, name in enumerate(model.linear) if name != "kd"]
        if loose.theta[th].any():
            for k in lobe:
                loose.x[k] |= free.x[k]
        if lobe and any(loose.x[k].any() for k in lobe) and all(np.all(~free.x[k] | loose.x[k] | was.x[k]) for k in lobe):
            loose.theta[th] |= free.theta[th]
    names = undetermined_names(fac, free, result.materials, loose)
    undetermined = [list(a) + [n for n in b if n not in a] for a, b in zip(result.undetermined, names)]
    return dataclasses.replace(result, sigma=sig, undetermined=undetermined)
