"""The scene: scene.json, its surfaces, materials and PLY meshes (docs/formats.md).

Only ``mesh``, ``material.brdf`` and ``material.ior`` are required; every photometric parameter
that is absent starts from docs/method.md §3's initial values and is listed in
:attr:`Material.defaulted`, so that a later stage knows which values the user supplied.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.core.workspace import Workspace, WorkspaceError, as_array, as_float, atomic_path, object_items, read_json, write_json

#: Parameters of each BRTDF model: name -> per-band (3 values) or scalar (1 value).
#: The models themselves live in inverse/forward/models.py; the file format owns the names.
BRDF_PARAMS: dict[str, dict[str, int]] = {
    "phong": {"kd": 3, "ks": 3, "ns": 1},
    "lambert": {"kd": 3},
    "ward": {"kd": 3, "ks": 3, "alpha": 1},
    "oren-nayar": {"kd": 3, "sigma": 1},
}
#: Secondary (ideal) reflection and transmission attenuations, every model.
PATH_PARAMS = ("r", "t")

#: docs/method.md §3 initial values (the dissertation's), and reasonable ones for the other models.
INITIAL = {"kd": 0.1, "ks": 0.1, "ns": 2**6.5, "alpha": 0.2, "sigma": 0.3, "r": 0.1, "t": 0.1}
#: Upper bound of each scalar nonlinear parameter (lower bound is > 0).
SCALAR_RANGE = {"ns": (1e-3, 2.0**20), "alpha": (1e-4, 1.0), "sigma": (0.0, np.pi / 2)}


@dataclass
class Material:
    """A surface's partially linear BRTDF plus its r, t and refraction index.

    ``params`` maps each name of ``BRDF_PARAMS[brdf]`` and ``r``, ``t`` to a float64 array
    (shape (3,) per band, or () for a scalar). ``ior`` is None for an opaque surface.
    """

    brdf: str
    params: dict[str, np.ndarray]
    ior: float | None = None
    defaulted: set[str] = field(default_factory=set)

    @property
    def transparent(self) -> bool:
        return self.ior is not None

    @property
    def given(self) -> set[str]:
        """The parameter names the user wrote in scene.json (not :attr:`defaulted`): the fit holds them."""
        return {n for n in self.params if n not in self.defaulted}

    def __getitem__(self, name: str) -> np.ndarray:
        return self.params[name]

    def to_json(self, given_only: bool = False) -> dict:
        """Every parameter (fit.json), or with ``given_only`` those not :attr:`defaulted` (scene.json:
        a value written there counts as given by the user, and the fit holds it)."""
        out = {"brdf": self.brdf}
        for k, v in self.params.items():
            if given_only and k in self.defaulted:
                continue
            out[k] = float(v) if np.ndim(v) == 0 else [float(x) for x in v]
        out["ior"] = self.ior
        return out

    @classmethod
    def from_json(cls, obj, path, where: str) -> "Material":
        if not isinstance(obj, dict):
            raise WorkspaceError(path, where, "an object with 'brdf' and 'ior'", got=obj)
        brdf = obj.get("brdf")
        if brdf not in BRDF_PARAMS:
            raise WorkspaceError(path, f"{where}.brdf", f"one of {sorted(BRDF_PARAMS)}", got=brdf)
        if "ior" not in obj:
            raise WorkspaceError(path, f"{where}.ior", "null (opaque) or a refraction index >= 1", got="missing")
        ior = obj["ior"]
        if ior is not None:
            ior = as_float(ior, path, f"{where}.ior", positive=True)
            if ior < 1.0:
                raise WorkspaceError(path, f"{where}.ior", "null (opaque) or a refraction index >= 1", got=ior)
        params, defaulted = {}, set()
        names = dict(BRDF_PARAMS[brdf], r=3, t=3)
        for name, size in names.items():
            if name not in obj or obj[name] is None:
                value = 0.0 if (name == "t" and ior is None) else INITIAL[name]
                params[name] = np.full(3, value) if size == 3 else np.float64(value)
                defaulted.add(name)
                continue
            raw = obj[name]
            if size == 3:
                if isinstance(raw, (int, float)) and not isinstance(raw, bool):
                    raw = [raw] * 3
                params[name] = as_array(raw, (3,), path, f"{where}.{name}", nonneg=True)
                if name in PATH_PARAMS and np.any(params[name] > 1):
                    raise WorkspaceError(path, f"{where}.{name}", "values in [0, 1]", got=raw)
            else:
                lo, hi = SCALAR_RANGE[name]
                val = as_float(raw, path, f"{where}.{name}")
                if not lo <= val <= hi:
                    raise WorkspaceError(path, f"{where}.{name}", f"a number in [{lo:g}, {hi:g}]", got=raw)
                params[name] = np.float64(val)
        if ior is None and np.any(params["t"] > 0):
            raise WorkspaceError(path, f"{where}.t", "0 for an opaque surface (ior null)", got=obj.get("t"))
        return cls(brdf, params, ior, defaulted)

    def copy(self) -> "Material":
        return copy.deepcopy(self)


@dataclass
class Mesh:
    """A triangle mesh in metres; ``normals`` are per-vertex shading normals or None (flat)."""

    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray | None = None

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        if self.normals is not None:
            self.normals = np.asarray(self.normals, dtype=np.float64).reshape(-1, 3)

    def is_closed(self) -> bool:
        """Every edge shared by exactly two triangles (a watertight, edge-manifold surface)."""
        tri = self.triangles
        edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        return bool(len(tri)) and bool(np.all(counts == 2))

    def face_normals(self) -> np.ndarray:
        v = self.vertices[self.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)

    def sample_points(self, n: int = 20000, seed: int = 0) -> np.ndarray:
        """``n`` points spread uniformly over the mesh's area (deterministic for a given seed)."""
        rng = np.random.default_rng(seed)
        v = self.vertices[self.triangles]
        area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
        tri = rng.choice(len(area), size=n, p=area / area.sum())
        a, b = rng.random(n), rng.random(n)
        flip = a + b > 1
        a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
        return v[tri, 0] + a[:, None] * (v[tri, 1] - v[tri, 0]) + b[:, None] * (v[tri, 2] - v[tri, 0])

    @classmethod
    def load(cls, path) -> "Mesh":
        path = Path(path)
        if not path.exists():
            raise WorkspaceError(path, expected="a mesh file (PLY or OBJ)", got="missing")
        from reflab.core.open3d_env import open3d
        o3d = open3d()

        m = o3d.io.read_triangle_mesh(str(path))
        if len(m.triangles) == 0:
            raise WorkspaceError(path, expected="a triangle mesh with at least one face")
        v = np.asarray(m.vertices)
        if not np.all(np.isfinite(v)):
            raise WorkspaceError(path, "vertices", "finite coordinates")
        normals = np.asarray(m.vertex_normals) if m.has_vertex_normals() else None
        return cls(v, np.asarray(m.triangles), normals)

    def save(self, path) -> Path:
        from reflab.core.open3d_env import open3d
        o3d = open3d()

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles.astype(np.int32)))
        if self.normals is not None:
            m.vertex_normals = o3d.utility.Vector3dVector(self.normals)
        with atomic_path(path) as tmp:
            if not o3d.io.write_triangle_mesh(str(tmp), m, write_ascii=False):
                raise OSError(f"{path}: Open3D could not write the mesh")
        return Path(path)


@dataclass
class Surface:
    """One named surface of the scene: its mesh, material and whether it carries a texture."""

    name: str
    mesh_path: str
    material: Material
    textured: bool = True
    mesh: Mesh | None = None
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        obj = dict(self.extra)
        obj.update(name=self.name, mesh=self.mesh_path, textured=self.textured,
                   material=self.material.to_json(given_only=True))
        return obj


@dataclass
class Scene:
    """The surfaces of a workspace, in scene.json order (surface index = list index)."""

    surfaces: list[Surface]
    root: Path = Path(".")

    def __len__(self):
        return len(self.surfaces)

    def __iter__(self):
        return iter(self.surfaces)

    def __getitem__(self, i):
        return self.surfaces[i]

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.surfaces]

    def index(self, name: str) -> int:
        return self.names.index(name)

    @property
    def any_transparent(self) -> bool:
        return any(s.material.transparent for s in self.surfaces)

    def to_json(self) -> dict:
        return {"surfaces": [s.to_json() for s in self.surfaces]}

    def save(self, path=None, *, write_meshes: bool = True) -> Path:
        """Write scene.json (and each surface's mesh, when it is loaded) under the scene's root."""
        path = Path(path) if path else Workspace(self.root).scene
        if write_meshes:
            for s in self.surfaces:
                if s.mesh is not None:
                    s.mesh.save(path.parent / s.mesh_path)
        return write_json(path, self.to_json())

    @classmethod
    def from_json(cls, obj: dict, path="scene.json", *, load_meshes: bool = True) -> "Scene":
        path = Path(path)
        surfaces, seen = [], set()
        for i, (where, item) in enumerate(object_items(obj.get("surfaces"), path, "surfaces", "surfaces")):
            name = item.get("name", f"surface{i}")
            if not isinstance(name, str) or not name or name in seen:
                raise WorkspaceError(path, f"{where}.name", "a unique non-empty string", got=name)
            seen.add(name)
            mesh_path = item.get("mesh")
            if not isinstance(mesh_path, str):
                raise WorkspaceError(path, f"{where}.mesh", "a mesh path relative to the workspace", got=mesh_path)
            if "material" not in item:
                raise WorkspaceError(path, f"{where}.material", "this field", got="missing")
            material = Material.from_json(item["material"], path, f"{where}.material")
            textured = item.get("textured", True)
            if not isinstance(textured, bool):
                raise WorkspaceError(path, f"{where}.textured", "true or false", got=textured)
            mesh = None
            if load_meshes:
                mesh_file = path.parent / mesh_path
                if not mesh_file.exists():
                    raise WorkspaceError(path, f"{where}.mesh", "an existing mesh file", got=str(mesh_file))
                mesh = Mesh.load(mesh_file)
                if material.transparent and not mesh.is_closed():
                    raise WorkspaceError(path, f"{where}.mesh", f"a closed mesh, because surface '{name}' is transparent (ior set); make a sheet a thin box", got=mesh_path)
            extra = {k: v for k, v in item.items() if k not in ("name", "mesh", "textured", "material")}
            surfaces.append(Surface(name, mesh_path, material, textured, mesh, extra))
        return cls(surfaces, path.parent)

    @classmethod
    def load(cls, path, *, load_meshes: bool = True) -> "Scene":
        return cls.from_json(read_json(path), path, load_meshes=load_meshes)
