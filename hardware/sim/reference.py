"""An independent reference renderer of the image-formation model, on Mitsuba 3's ray casting.

It renders exactly docs/formats.md's "scene.json" model (docs/method.md §1): at a node on surface s

    B = Σ_k V_k (I_k / d_k²) g_s(n, l_k, v) · x_s  +  r_s F B_refl  +  t_s (1 − F) B_refr

with ``ior`` null = opaque (F = 1, no refracted branch), shadow rays blocked by every surface
(transparent ones included), at most ``depth`` internal nodes per path, 0 for rays that leave
the scene, one ray per pixel through the undistorted pixel centre.

It shares no code with ``inverse/`` (its own wavefront Whitted loop, shading, Fresnel and Snell)
so that agreeing with the forward model of ``reflab.inverse.forward.trees`` / ``reflab.inverse.forward.rendering`` means
something: Mitsuba (Embree) finds the hits, numpy shades them in float64. Which medium a ray
travels in is tracked along the path (it starts in air at the camera), so refraction does not
depend on how a closed mesh's triangles are oriented.
"""
from __future__ import annotations

import time

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.lights import Lights
from reflab.reconstruction.scene import Scene

#: Offset (metres) of secondary and shadow ray origins off the surface, against self-hits.
EPS = 1e-5
#: Models this renderer shades.
MODELS = ("phong", "lambert", "ward", "oren-nayar")


def fresnel(cos_i: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unpolarised Fresnel reflectance of a dielectric interface (docs/method.md eq. 2.3).

    Parameters
    ----------
    cos_i : (N,) ndarray
        Cosine of the incidence angle, in [0, 1].
    eta : (N,) ndarray
        Ratio n_incident / n_transmitted.

    Returns
    -------
    F : (N,) ndarray
        Reflectance; 1 under total internal reflection.
    cos_t : (N,) ndarray
        Cosine of the refraction angle (0 under total internal reflection).
    """
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin2_t = eta**2 * (1.0 - cos_i**2)
    tir = sin2_t >= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, 1.0))
    # n1 cos_i vs n2 cos_t with n1/n2 = eta, written with eta to stay dimensionless.
    rs = (eta * cos_i - cos_t) / np.maximum(eta * cos_i + cos_t, 1e-300)
    rp = (cos_i - eta * cos_t) / np.maximum(cos_i + eta * cos_t, 1e-300)
    F = np.where(tir, 1.0, 0.5 * (rs**2 + rp**2))
    return F, np.where(tir, 0.0, cos_t)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


class _Caster:
    """Mitsuba scene with one mesh shape per surface; hits come back as numpy arrays."""

    def __init__(self, scene: Scene):
        from reflab.core.mitsuba_env import mitsuba

        self.mi = mi = mitsuba()
        self.shapes, self.face_normals, self.smooth, self.vertices, self.triangles = [], [], [], [], []
        shapes = {}
        for i, surf in enumerate(scene):
            if surf.mesh is None:
                raise ValueError(f"render_reference: surface '{surf.name}' has no mesh loaded")
            m = surf.mesh
            has_n = m.normals is not None
            shape = mi.Mesh(surf.name, len(m.vertices), len(m.triangles), has_vertex_normals=has_n)
            params = mi.traverse(shape)
            params["vertex_positions"] = mi.Float(m.vertices.astype(np.float32).ravel())
            params["faces"] = mi.UInt32(m.triangles.astype(np.uint32).ravel())
            if has_n:
                params["vertex_normals"] = mi.Float(_unit(m.normals).astype(np.float32).ravel())
            params.update()
            shapes[f"s{i:04d}"] = shape
            self.shapes.append(shape)
            self.face_normals.append(m.face_normals())
            self.vertices.append(m.vertices)
            self.triangles.append(m.triangles)
            self.smooth.append(has_n)
        # optimize=False keeps one shape per surface (Mitsuba merges shapes whose BSDFs are equal).
        self.scene = mi.load_dict({"type": "scene", **shapes}, optimize=False)

    def _ray(self, o, d, tmax=None):
        mi = self.mi
        ray = mi.Ray3f(mi.Point3f(o.T.astype(np.float32)), mi.Vector3f(d.T.astype(np.float32)))
        if tmax is not None:
            ray.maxt = mi.Float(tmax.astype(np.float32))
        return ray

    def intersect(self, o: np.ndarray, d: np.ndarray):
        """Nearest hits of rays (o, d): (hit mask, t, surface index, geometric normal, shading normal)."""
        n = len(o)
        if n == 0:  # Dr.Jit aborts the process on a zero-length ray batch ("jit_var(r0): unknown variable!")
            return (np.zeros(0, dtype=bool), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 3)),
                    np.zeros((0, 3)))
        si = self.scene.ray_intersect(self._ray(o, d))
        hit = np.array(si.is_valid(), dtype=bool).reshape(n)
        t = np.array(si.t, dtype=np.float64).reshape(n)
        prim = np.array(si.prim_index, dtype=np.int64).reshape(n)
        surface = np.full(n, -1, dtype=np.int64)
        ng = np.zeros((n, 3))
        for i, shape in enumerate(self.shapes):
            sel = hit & np.array(si.shape == self.mi.ShapePtr(shape), dtype=bool).reshape(n)
            surface[sel] = i
            ng[sel] = self.face_normals[i][prim[sel]]
        ns = ng.copy()
        if any(self.smooth):
            sh = np.array(si.sh_frame.n, dtype=np.float64).reshape(3, n).T
            smooth = np.isin(surface, np.flatnonzero(self.smooth))
            ns[smooth] = _unit(sh[smooth])
        hit &= surface >= 0
        t = np.where(hit, t, 0.0)
        # Refine Embree's float32 distance in float64 on the hit triangle's plane (kept if close).
        v0 = np.zeros((n, 3))
        for i in range(len(self.shapes)):
            sel = surface == i
            v0[sel] = self.vertices[i][self.triangles[i][prim[sel], 0]]
        den = np.sum(d * ng, axis=1)
        t64 = np.divide(np.sum((v0 - o) * ng, axis=1), den, out=t.copy(), where=hit & (np.abs(den) > 1e-9))
        close = hit & (np.abs(t64 - t) <= 1e-4 * (1.0 + np.abs(t)))
        t = np.where(close, t64, t)
        return hit, t, surface, ng, ns

    def occluded(self, o: np.ndarray, d: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        """Whether anything lies on the segments o + s d, 0 < s < tmax."""
        if len(o) == 0:  # as in intersect: an empty batch would abort the process
            return np.zeros(0, dtype=bool)
        return np.array(self.scene.ray_test(self._ray(o, d, tmax)), dtype=bool).reshape(len(o))


def _shade(material, kd: np.ndarray, n: np.ndarray, v: np.ndarray, l: np.ndarray) -> np.ndarray:
    """``g · x`` of the surface's model for one light (lit side only): (N, 3) per unit irradiance.

    Written from the models' textbook definitions with explicit angles, not from inverse/forward/models.py.
    """
    cos_l = np.clip(np.sum(n * l, axis=1), 0.0, 1.0)
    cos_v = np.clip(np.sum(n * v, axis=1), 1e-6, 1.0)
    out = kd * cos_l[:, None]
    if material.brdf == "phong":
        cos_h = np.clip(np.sum(n * _unit(l + v), axis=1), 0.0, 1.0)
        out = out + material["ks"] * (cos_h ** material["ns"])[:, None]
    elif material.brdf == "ward":
        # Isotropic Ward (1992): ks exp(-tan²δ / α²) / (4π α² sqrt(cos θi cos θo)), times cos θi.
        delta = np.arccos(np.clip(np.sum(n * _unit(l + v), axis=1), -1.0, 1.0))
        alpha = float(material["alpha"])
        lobe = np.where(delta < np.pi / 2, np.exp(-np.tan(np.minimum(delta, 1.5707)) ** 2 / alpha**2), 0.0)
        spec = lobe / (4 * np.pi * alpha**2 * np.sqrt(np.maximum(cos_l, 1e-300) * cos_v)) * cos_l
        out = out + material["ks"] * spec[:, None]
    elif material.brdf == "oren-nayar":
        # Qualitative Oren-Nayar (1994): cos θi (A + B max(0, cos(φi − φo)) sin α tan β).
        s2 = float(material["sigma"]) ** 2
        a, b = 1 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09)
        th_i, th_o = np.arccos(cos_l), np.arccos(cos_v)
        l_t, v_t = _unit(l - cos_l[:, None] * n), _unit(v - cos_v[:, None] * n)
        cos_phi = np.clip(np.sum(l_t * v_t, axis=1), 0.0, 1.0)
        big, small = np.maximum(th_i, th_o), np.minimum(th_i, th_o)
        out = kd * (cos_l * (a + b * cos_phi * np.sin(big) * np.tan(small)))[:, None]
    return out


def render_reference(scene: Scene, camera: Camera, lights: Lights, depth: int = 3, albedo=None,
                     stats: dict | None = None) -> np.ndarray:
    """Render the scene with its materials by Whitted ray tracing on Mitsuba's ray casting.

    Parameters
    ----------
    scene : Scene
        Surfaces with meshes loaded; each material's model must be in :data:`MODELS`.
    camera : Camera
    lights : Lights
    depth : int
        Maximum number of internal nodes on a path (docs/method.md's D), >= 1.
    albedo : callable, optional
        ``albedo(surface_index, points (N, 3)) -> (N, 3)``: per-point ``kd`` (a texture); the
        materials' ``kd`` when omitted.
    stats : dict, optional
        Filled with counts: rays cast per kind, nodes per level, refractions, total internal
        reflections, seconds.

    Returns
    -------
    (H, W, 3) ndarray, float64
        Linear radiance per pixel.
    """
    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < 1:
        raise ValueError(f"render_reference: depth must be an integer >= 1, got {depth!r}")
    for i, s in enumerate(scene):
        if s.material.brdf not in MODELS:
            raise ValueError(f"render_reference: surface {i} '{s.name}' uses brdf '{s.material.brdf}'; "
                             f"this renderer shades {MODELS}")
    start = time.perf_counter()
    caster = _Caster(scene)
    mats = [s.material for s in scene]
    r_s = np.array([m["r"] for m in mats])
    t_s = np.array([m["t"] for m in mats])
    ior = np.array([np.nan if m.ior is None else m.ior for m in mats])
    light_pos, light_int = lights.positions, lights.intensities
    npix = camera.width * camera.height
    image = np.zeros((npix, 3))
    counts = {"primary": 0, "secondary": 0, "shadow": 0, "refractions": 0, "tir": 0, "nodes_per_level": []}

    o, d = camera.pixel_rays()
    pixel = np.arange(npix)
    weight = np.ones((npix, 3))
    inside = np.full(npix, -1)  # index of the closed transparent surface the ray travels in, -1 = air
    for level in range(1, depth + 1):
        counts["primary" if level == 1 else "secondary"] += len(o)
        hit, t, surface, ng, ns = caster.intersect(o, d)
        o, d, t, surface, ng, ns = o[hit], d[hit], t[hit], surface[hit], ng[hit], ns[hit]
        pixel, weight, inside = pixel[hit], weight[hit], inside[hit]
        counts["nodes_per_level"].append(int(len(o)))
        if not len(o):
            break
        p = o + t[:, None] * d
        # Normals face the incoming ray (the viewer's side); open meshes are two-sided.
        ng = np.where((np.sum(ng * d, axis=1) > 0)[:, None], -ng, ng)
        ns = np.where((np.sum(ns * ng, axis=1) < 0)[:, None], -ns, ns)
        v = -d

        kd = np.array([mats[s]["kd"] for s in range(len(mats))])[surface]
        if albedo is not None:
            kd = np.zeros((len(p), 3))
            for s in np.unique(surface):
                sel = surface == s
                kd[sel] = np.asarray(albedo(int(s), p[sel]), dtype=np.float64).reshape(-1, 3)
            if not np.all(np.isfinite(kd)):
                raise ValueError("render_reference: the albedo function returned NaN/inf")

        radiance = np.zeros((len(p), 3))
        origin = p + EPS * ng
        for k in range(len(light_pos)):
            to_light = light_pos[k] - p
            dist2 = np.maximum(np.sum(to_light**2, axis=1), 1e-300)
            dist = np.sqrt(dist2)
            l = to_light / dist[:, None]
            # A lamp within EPS of the point has no defined direction: it does not light it.
            lit = (np.sum(ns * l, axis=1) > 0) & (np.sum(ng * l, axis=1) > 0) & (dist > EPS)
            idx = np.flatnonzero(lit)
            counts["shadow"] += len(idx)
            lit[idx] = ~caster.occluded(origin[idx], l[idx], dist[idx] - 2 * EPS)
            idx = np.flatnonzero(lit)
            for s in np.unique(surface[idx]):
                sel = idx[surface[idx] == s]
                radiance[sel] += light_int[k] / dist2[sel, None] * _shade(mats[s], kd[sel], ns[sel], v[sel], l[sel])
        contrib = weight * radiance
        for c in range(3):
            image[:, c] += np.bincount(pixel, weights=contrib[:, c], minlength=npix)
        if level == depth:
            break

        # Ideal branches: mirror reflection, and Snell refraction at dielectrics.
        cos_i = np.clip(-np.sum(d * ns, axis=1), 0.0, 1.0)
        transparent = ~np.isnan(ior[surface])
        entering = inside != surface
        eta = np.where(entering, 1.0 / np.where(transparent, ior[surface], 1.0), np.where(transparent, ior[surface], 1.0))
        F, cos_t = fresnel(cos_i, eta)
        F = np.where(transparent, F, 1.0)
        tir = transparent & (eta**2 * (1.0 - cos_i**2) >= 1.0)
        counts["tir"] += int(tir.sum())
        refr = transparent & ~tir
        counts["refractions"] += int(refr.sum())

        d_refl = _unit(d + 2.0 * cos_i[:, None] * ns)
        w_refl = weight * r_s[surface] * F[:, None]
        d_refr = _unit(eta[:, None] * d + (eta * cos_i - cos_t)[:, None] * ns)
        w_refr = weight * t_s[surface] * (1.0 - F)[:, None]
        # Parameter-aware pruning: a branch with zero weight adds nothing to the image.
        keep_refl = np.any(w_refl > 0, axis=1)
        keep_refr = refr & np.any(w_refr > 0, axis=1)
        o = np.concatenate([p[keep_refl] + EPS * ng[keep_refl], p[keep_refr] - EPS * ng[keep_refr]])
        d = np.concatenate([d_refl[keep_refl], d_refr[keep_refr]])
        weight = np.concatenate([w_refl[keep_refl], w_refr[keep_refr]])
        pixel = np.concatenate([pixel[keep_refl], pixel[keep_refr]])
        inside = np.concatenate([inside[keep_refl], np.where(entering, surface, -1)[keep_refr]])
        if not len(o):
            break

    counts["seconds"] = time.perf_counter() - start
    if stats is not None:
        stats.update(counts)
    out = image.reshape(camera.height, camera.width, 3)
    if not np.all(np.isfinite(out)):
        raise FloatingPointError("render_reference: non-finite radiance (check the lights and materials)")
    return out
