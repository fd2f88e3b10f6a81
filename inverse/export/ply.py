"""Binary PLY meshes with per-vertex normals and texture coordinates (numpy only).

Mitsuba 3, MeshLab, Blender and Open3D read ``x y z [nx ny nz] [u v]`` vertices and
``vertex_indices`` faces; MeshLab finds the texture through a ``comment TextureFile`` line.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_ply(path, vertices, triangles, *, normals=None, uv=None, uv_names=("u", "v"), comments=()) -> Path:
    """Write a binary little-endian PLY atomically.

    Parameters
    ----------
    path : path-like
    vertices : (V, 3) array
    triangles : (T, 3) int array
    normals : (V, 3) array, optional
    uv : (V, 2) array, optional
        Written as given (the caller picks the v direction its readers expect).
    uv_names : (str, str)
        The vertex property names of the texture coordinates.
    comments : iterable of str
        Header comments (``TextureFile name.png`` for MeshLab).
    """
    from reflab.core.workspace import atomic_write

    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = [vertices]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        columns.append(np.asarray(normals, np.float64).reshape(-1, 3))
    if uv is not None:
        fields += [(uv_names[0], "<f4"), (uv_names[1], "<f4")]
        columns.append(np.asarray(uv, np.float64).reshape(-1, 2))
    data = np.concatenate(columns, axis=1)
    if not np.all(np.isfinite(data)):
        raise ValueError(f"{path}: refusing to write a mesh with NaN/inf values")
    vert = np.empty(len(vertices), dtype=fields)
    for i, (name, _) in enumerate(fields):
        vert[name] = data[:, i]
    face = np.empty(len(triangles), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, triangles
    header = ["ply", "format binary_little_endian 1.0", *[f"comment {c}" for c in comments],
              f"element vertex {len(vertices)}", *[f"property float {n}" for n, _ in fields],
              f"element face {len(triangles)}", "property list uchar int vertex_indices", "end_header"]
    with atomic_write(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vert.tobytes())
        f.write(face.tobytes())
    return Path(path)


def read_ply(path) -> dict:
    """Read a PLY this module wrote: ``{"vertex": {name: (V,) array}, "faces": (T, 3), "comments": [...]}``."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    names, comments, counts = [], [], {}
    for line in lines:
        parts = line.split()
        if parts[0] == "comment":
            comments.append(line[8:])
        elif parts[0] == "element":
            counts[parts[1]] = int(parts[2])
        elif parts[0] == "property" and parts[1] == "float":
            names.append(parts[2])
    vert = np.frombuffer(raw, dtype=[(n, "<f4") for n in names], count=counts["vertex"], offset=end)
    face = np.frombuffer(raw, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=counts["face"],
                         offset=end + vert.nbytes)
    return {"vertex": {n: vert[n].astype(np.float64) for n in names}, "faces": face["i"].astype(np.int64),
            "comments": comments}
