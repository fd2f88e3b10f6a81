"""reflab export: the recovered model as a Mitsuba 3 scene, a glTF binary and PLY meshes with UVs.

The workspace is the textured simulated lab (ground, textured box and tile, a glass sheet and a
mirror) at 80x60 with an undistorted camera (no export format has lens distortion), its texture
recovered by ``reflab texture`` with the true materials of scene.json. Plain Mitsuba renders the
export from the input camera and ``reflab render`` the workspace: they must agree (docs/export.md).
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest

W, H = 80, 60


@pytest.fixture(scope="module")
def textured_ws(tmp_path_factory):
    from reflab.core.images import write_image
    from reflab.hardware.sim.lab import build_lab, write_lab
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees
    from reflab.inverse.stages import TextureOptions, texture

    root = tmp_path_factory.mktemp("exportws")
    lab = build_lab(W, H)
    lab.camera.dist = np.zeros(5)
    write_lab(root, lab)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    image = render(trees, [s.material for s in lab.scene], lab.lights.intensities,
                   kd_nodes=lab.albedo_at(trees.surface, trees.point))
    write_image(root / "input.exr", image)
    texture(TextureOptions(root))
    return root


def _mitsuba_psnr(root, out, *, spp: int, factor: int = 3) -> float:
    """PSNR (dB, peak of the reflab render) between plain Mitsuba's render of ``out/scene.xml`` and
    ``reflab render`` of ``root``, over the pixels that see a surface. Mitsuba renders at ``factor``
    times the size and the centre sample of each pixel is kept: reflab's pixel is the ray through
    its centre, Mitsuba's the pixel's area."""
    from reflab.core.mitsuba_env import mitsuba
    from reflab.inverse.stages import render_workspace

    ref, info = render_workspace(root)
    mi = mitsuba()
    scene = mi.load_file(str(out / "scene.xml"), spp=spp, width=W * factor, height=H * factor)
    img = np.array(mi.render(scene), dtype=np.float64)[factor // 2::factor, factor // 2::factor]
    trees = info["trees"]
    seen = np.zeros(W * H, bool)
    seen[trees.pixel[trees.level == 1]] = True
    seen = seen.reshape(H, W)
    assert seen.mean() > 0.9 and np.all(np.isfinite(img))
    mse = np.mean((img[seen] - ref[seen]) ** 2)
    return float(10 * np.log10(ref[seen].max() ** 2 / mse))


def test_mitsuba_export_renders_as_reflab(textured_ws, tmp_path):
    from reflab.inverse.export.ply import read_ply
    from reflab.inverse.export.stage import ExportOptions, export

    r = export(ExportOptions(textured_ws, format="mitsuba", output=tmp_path / "mi"))
    assert r.path == tmp_path / "mi" / "scene.xml" and r.warnings == []
    text = r.path.read_text()
    for plugin in ("conductor", "dielectric", "roughconductor", "blendbsdf", "point", "perspective"):
        assert f'type="{plugin}"' in text
    for name in ("ground", "box", "tile"):
        assert (tmp_path / "mi" / "textures" / f"{name}.exr").is_file()
    box = read_ply(tmp_path / "mi" / "meshes" / "box.ply")
    assert {"u", "v"} <= set(box["vertex"]) and len(box["vertex"]["x"]) == 24  # one vertex per face corner
    # Measured 32.4 dB (32.5 at 1024 spp): the rest is Mitsuba's diffuse interreflection, which
    # reflab's model leaves out, and noise (docs/export.md).
    assert _mitsuba_psnr(textured_ws, tmp_path / "mi", spp=256) > 32.0


def test_mitsuba_principal_point(textured_ws, tmp_path):
    """A principal point off the image centre moves Mitsuba's view as it moves reflab's."""
    import json

    from reflab.inverse.export.stage import ExportOptions, export

    ws = tmp_path / "ws"
    ws.mkdir()
    for name in ("lights.json", "scene.json", "meshes"):
        (shutil.copytree if name == "meshes" else shutil.copy)(textured_ws / name, ws / name)
    cam = json.loads((textured_ws / "camera.json").read_text())
    cam["K"][0][2] += 12.0
    cam["K"][1][2] -= 7.0
    (ws / "camera.json").write_text(json.dumps(cam))
    r = export(ExportOptions(ws, output=tmp_path / "mi"))
    assert any("texture" in w for w in r.warnings)
    # Measured 31.6 dB; with either offset's sign reversed 13 dB.
    assert _mitsuba_psnr(ws, tmp_path / "mi", spp=64) > 31.0


def test_gltf_export(textured_ws, tmp_path):
    from reflab.core.open3d_env import open3d
    from reflab.core.workspace import Workspace
    from reflab.inverse.export.gltf import read_accessor, read_glb, read_image
    from reflab.inverse.export.stage import ExportOptions, export
    from reflab.inverse.texture.solve import load_materials, load_texture_maps
    from reflab.reconstruction.scene import Scene

    r = export(ExportOptions(textured_ws, format="gltf", output=tmp_path / "model.glb"))
    assert r.path == tmp_path / "model.glb"
    doc, blob = read_glb(r.path)
    scene = Scene.load(Workspace(textured_ws).scene)
    maps = load_texture_maps(textured_ws, scene)
    materials, _ = load_materials(textured_ws, scene)
    meshes = {m["name"]: m for m in doc["meshes"]}
    assert sorted(meshes) == sorted(scene.names)
    for s, surf in enumerate(scene):
        prim = meshes[surf.name]["primitives"][0]
        assert {"POSITION", "NORMAL", "TEXCOORD_0"} <= set(prim["attributes"])
        pos = read_accessor(doc, blob, prim["attributes"]["POSITION"])
        uv = read_accessor(doc, blob, prim["attributes"]["TEXCOORD_0"])
        idx = read_accessor(doc, blob, prim["indices"])
        assert len(idx) == 3 * len(surf.mesh.triangles) and np.all((uv >= 0) & (uv <= 1))
        # The workspace mesh's vertices (float32 in the file), split where normals or UVs differ.
        assert np.allclose(np.unique(pos.round(5), axis=0), np.unique(surf.mesh.vertices.round(5), axis=0), atol=2e-5)
        pbr = doc["materials"][prim["material"]]["pbrMetallicRoughness"]
        if s in maps:
            _, kd, mask = maps[s]
            image = read_image(doc, blob, doc["textures"][pbr["baseColorTexture"]["index"]]["source"])
            assert image.shape == kd.shape
            # 8-bit sRGB keeps the recovered albedo's mean within 0.3 %.
            assert np.allclose(image[mask].mean(0), kd[mask].mean(0), rtol=3e-3, atol=1e-3)
        elif surf.name != "mirror" and not surf.material.transparent:
            assert np.allclose(pbr["baseColorFactor"][:3], materials[s]["kd"])
    sheet = doc["materials"][scene.index("sheet")]["extensions"]
    assert sheet["KHR_materials_ior"]["ior"] == pytest.approx(scene[scene.index("sheet")].material.ior)
    assert sheet["KHR_materials_transmission"]["transmissionFactor"] == pytest.approx(0.92)
    mirror = doc["materials"][scene.index("mirror")]["pbrMetallicRoughness"]
    assert mirror["metallicFactor"] == 1.0 and mirror["baseColorFactor"][:3] == pytest.approx([0.85] * 3)
    lamps = doc["extensions"]["KHR_lights_punctual"]["lights"]
    lights = [n for n in doc["nodes"] if "KHR_lights_punctual" in n.get("extensions", {})]
    truth = json_lights(textured_ws)
    assert len(lamps) == len(lights) == 2
    for node, (pos, intensity) in zip(lights, truth):
        lamp = lamps[node["extensions"]["KHR_lights_punctual"]["light"]]
        assert np.allclose(node["translation"], pos)
        assert np.allclose(np.array(lamp["color"]) * lamp["intensity"], np.pi * np.asarray(intensity))
    assert [n for n in doc["nodes"] if "camera" in n] and doc["cameras"][0]["type"] == "perspective"
    # An independent reader (Open3D's Assimp) finds the five meshes, their UVs and three textures.
    model = open3d().io.read_triangle_model(str(r.path))
    assert sorted(m.mesh_name for m in model.meshes) == sorted(scene.names)
    assert all(m.mesh.has_triangle_uvs() for m in model.meshes)
    assert sum(m.albedo_img is not None for m in model.materials) == 3


def json_lights(root):
    import json

    return [(l["position"], l["intensity"]) for l in json.loads((root / "lights.json").read_text())["lights"]]


def test_ply_export_uvs_sample_the_texture(textured_ws, tmp_path):
    """Bilinear lookups at the exported UVs give what ``reflab render`` samples at the same points."""
    from reflab.core.images import read_image
    from reflab.core.workspace import Workspace
    from reflab.inverse.export.ply import read_ply
    from reflab.inverse.export.stage import ExportOptions, export
    from reflab.inverse.texture.solve import load_texture_maps, sample_texture
    from reflab.reconstruction.scene import Scene

    out = tmp_path / "ply"
    export(ExportOptions(textured_ws, format="ply", output=out))
    scene = Scene.load(Workspace(textured_ws).scene)
    maps = load_texture_maps(textured_ws, scene)
    assert (out / "materials.json").is_file()
    for s, surf in enumerate(scene):
        ply = read_ply(out / f"{surf.name}.ply")
        assert {"texture_u", "texture_v"} <= set(ply["vertex"])
        if s not in maps:
            continue
        assert f"TextureFile {surf.name}.png" in ply["comments"] and (out / f"{surf.name}.png").is_file()
        tex = read_image(out / f"{surf.name}.exr").astype(np.float64)
        tmap, kd, mask = maps[s]
        faces = ply["faces"]
        uv = np.stack([ply["vertex"]["texture_u"], 1.0 - ply["vertex"]["texture_v"]], axis=1)
        rng = np.random.default_rng(0)
        tri = rng.integers(len(faces), size=4000)
        bary = rng.dirichlet([1, 1, 1], size=len(tri))
        p_uv = np.einsum("tk,tkc->tc", bary, uv[faces[tri]])
        # Bilinear lookup as a renderer does it: texel centres at (i + 0.5) / size.
        x, y = p_uv[:, 0] * tmap.width - 0.5, p_uv[:, 1] * tmap.height - 0.5
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = x - x0, y - y0
        at = lambda r, c: tex[np.clip(r, 0, tmap.height - 1), np.clip(c, 0, tmap.width - 1)]
        got = ((1 - fx) * (1 - fy))[:, None] * at(y0, x0) + (fx * (1 - fy))[:, None] * at(y0, x0 + 1) \
            + ((1 - fx) * fy)[:, None] * at(y0 + 1, x0) + (fx * fy)[:, None] * at(y0 + 1, x0 + 1)
        want = sample_texture(tmap, kd, mask, tri, bary[:, 1:])  # the mesh's triangle order
        # Where all four texels are known (elsewhere reflab renormalises over the known ones).
        index, _ = tmap.bilinear(tri, bary[:, 1:])
        ok = mask.ravel()[index].all(axis=1)
        assert ok.sum() > 200
        assert np.abs(got[ok] - want[ok]).max() < 2e-3


def test_cli_export_and_bad_format(textured_ws, tmp_path, capsys):
    from reflab.app.cli import main

    assert main(["export", str(textured_ws), "--format", "ply", "-o", str(tmp_path / "p")]) == 0
    assert (tmp_path / "p" / "ground.ply").is_file()
    with pytest.raises(SystemExit) as exc:
        main(["export", str(textured_ws), "--format", "obj"])
    assert exc.value.code == 2


def test_cancelled_export_writes_nothing(textured_ws, tmp_path):
    from reflab.core.task import Cancelled, Task
    from reflab.inverse.export.stage import ExportOptions, export

    task = Task()
    task.cancel()
    with pytest.raises(Cancelled):
        export(ExportOptions(textured_ws, output=tmp_path / "mi"), task)
    assert not (tmp_path / "mi" / "scene.xml").exists()
