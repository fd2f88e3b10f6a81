"""The workspace's trees cache: built once, reused while nothing the trees depend on changes."""
import numpy as np
import pytest

from reflab.calibration.camera import Camera
from reflab.calibration.lights import Lights
from reflab.hardware.sim.lab import build_lab, write_lab
from reflab.core.task import Cancelled, Task
from reflab.core.workspace import Workspace, read_json, write_json
from reflab.inverse.forward.trees import _ARRAYS, build_trees, trees_for_workspace
from reflab.reconstruction.scene import Mesh, Scene


def _load(ws):
    return Scene.load(ws.scene), Camera.load(ws.camera), Lights.load(ws.lights)


def _trees(ws, log):
    return trees_for_workspace(ws, *_load(ws), depth=3, log=log.append)


def test_trees_cache_reused_and_invalidated(tmp_path):
    ws = Workspace(tmp_path / "ws")
    write_lab(ws.root, build_lab(48, 36), materials=False)
    log = []
    first = _trees(ws, log)
    assert first.stats["cache"] == "built" and log[-1].startswith("trees: built in")
    assert len(list(ws.cache.glob("trees-*.npz"))) == 1

    # Same inputs (files re-read): the cached trees come back, identical to a fresh build.
    again = _trees(ws, log)
    assert again.stats["cache"] == "reused" and log[-1].startswith("trees: reused cache")
    fresh = build_trees(*_load(ws), depth=3)
    assert again.key == fresh.key and again.paths == fresh.paths
    for name in _ARRAYS:
        np.testing.assert_array_equal(getattr(again, name), getattr(fresh, name), err_msg=name)

    # A mesh moved by 1 mm: rebuilt, and the new trees see the moved box.
    box = ws.root / "meshes" / "box.ply"
    mesh = Mesh.load(box)
    Mesh(mesh.vertices + [0.0, 0.0, 0.001], mesh.triangles, mesh.normals).save(box)
    moved = _trees(ws, log)
    assert moved.stats["cache"] == "built" and log[-1].startswith("trees: built in")
    assert moved.key != first.key
    box_i = Scene.load(ws.scene).index("box")
    on_box = (moved.surface == box_i) & (moved.level == 1)
    assert not np.array_equal(moved.point[on_box], first.point[(first.surface == box_i) & (first.level == 1)])
    assert _trees(ws, log).stats["cache"] == "reused"

    # Other inputs the trees depend on: a lamp's position, r given as 0 (pruning), the depth.
    lights = read_json(ws.lights)
    lights["lights"][0]["position"][0] += 0.01
    write_json(ws.lights, lights)
    assert _trees(ws, log).stats["cache"] == "built"
    scene = read_json(ws.scene)
    scene["surfaces"][0]["material"].pop("r")  # the ground no longer declared matte: its reflections are followed
    write_json(ws.scene, scene)
    assert _trees(ws, log).stats["cache"] == "built"
    assert trees_for_workspace(ws, *_load(ws), depth=2).stats["cache"] == "built"
    # A lamp's intensity is not a tree input.
    lights["lights"][1]["intensity"] = [0.5, 0.5, 0.5]
    write_json(ws.lights, lights)
    assert _trees(ws, log).stats["cache"] == "reused"
    assert len(list(ws.cache.glob("trees-*.npz"))) <= 4  # older files pruned


def test_trees_cache_unreadable_file_is_rebuilt(tmp_path):
    ws = Workspace(tmp_path / "ws")
    write_lab(ws.root, build_lab(32, 24), materials=False)
    log = []
    trees = _trees(ws, log)
    (path,) = ws.cache.glob("trees-*.npz")
    path.write_bytes(b"not an npz file")
    again = _trees(ws, log)
    assert again.stats["cache"] == "built" and len(again) == len(trees)
    assert _trees(ws, log).stats["cache"] == "reused"


def test_trees_cancelled_build_writes_nothing(tmp_path):
    ws = Workspace(tmp_path / "ws")
    write_lab(ws.root, build_lab(32, 24), materials=False)
    task = Task()
    task.cancel()
    with pytest.raises(Cancelled):
        trees_for_workspace(ws, *_load(ws), depth=3, task=task)
    assert not ws.cache.exists() or not list(ws.cache.glob("trees-*"))


def test_trees_cache_keeps_the_file_in_use(tmp_path, monkeypatch):
    """Relightings fill the cache; the workspace's own trees, reused in between, are not pruned."""
    import time

    import reflab.inverse.forward.trees as trees_module
    from reflab.calibration.lights import PointLight

    monkeypatch.setattr(trees_module, "CACHE_KEEP", 2)
    ws = Workspace(tmp_path / "ws")
    write_lab(ws.root, build_lab(32, 24), materials=False)
    scene, camera, lights = _load(ws)
    assert trees_for_workspace(ws, scene, camera, lights).stats["cache"] == "built"
    for dx in (0.01, 0.02, 0.03):
        time.sleep(0.02)
        moved = Lights([PointLight(lt.position + [dx, 0.0, 0.0], lt.intensity) for lt in lights])
        assert trees_for_workspace(ws, scene, camera, moved).stats["cache"] == "built"
        time.sleep(0.02)
        assert trees_for_workspace(ws, scene, camera, lights).stats["cache"] == "reused"
    assert len(list(ws.cache.glob("trees-*.npz"))) == 2


def test_trees_cache_written_in_background_is_read_whole(tmp_path, monkeypatch):
    """A cache file written on a thread (the fit's) is the trees built, and a read waits for it."""
    import threading

    from reflab.inverse.forward.trees import Trees, wait_for_saves

    ws = Workspace(tmp_path / "ws")
    write_lab(ws.root, build_lab(48, 36), materials=False)
    release, save = threading.Event(), Trees.save

    def held_save(self, path):  # the write starts only when the test says so
        release.wait(30)  # a bound only: a synchronous write would otherwise hang the test
        return save(self, path)

    monkeypatch.setattr(Trees, "save", held_save)
    log = []
    built = trees_for_workspace(ws, *_load(ws), depth=3, log=log.append, background=True)
    # Returned before its file was written: nothing in the cache, no line logged yet.
    assert built.stats["cache"] == "built" and not list(ws.cache.glob("*trees-*")) and log == []
    release.set()
    # Read again at once: it waits for the write and reads the file whole.
    again = trees_for_workspace(ws, *_load(ws), depth=3, log=log.append)
    assert again.stats["cache"] == "reused"
    wait_for_saves()
    # The build's line comes when its file is written, before the read that waited for it.
    assert len(log) == 2 and log[0].startswith("trees: built in") and "cached as" in log[0]
    assert log[1].startswith("trees: reused cache")
    files = list(ws.cache.glob("trees-*.npz"))
    assert len(files) == 1 and not list(ws.cache.glob(".trees-*"))  # no temporary file left
    loaded = Trees.load(files[0])
    for name in _ARRAYS:
        np.testing.assert_array_equal(getattr(loaded, name), getattr(built, name), err_msg=name)
        np.testing.assert_array_equal(getattr(again, name), getattr(built, name), err_msg=name)
    assert loaded.paths == built.paths and loaded.key == built.key


def test_fit_workspace_returns_with_its_trees_cached(tmp_path):
    """fit_workspace writes its trees cache on a thread and waits for it before returning."""
    from reflab.hardware.sim.lab import user_workspace
    from reflab.inverse.fit.workspace_fit import fit_workspace
    from reflab.inverse.forward import trees as trees_module

    ws = Workspace(tmp_path / "ws")
    user_workspace(ws.root, 40, 30, textured=False)
    fit_workspace(ws.root, texture_rounds=0)
    assert not trees_module._SAVING  # nothing still being written
    files = list(ws.cache.glob("trees-*.npz"))
    assert len(files) == 1
    assert trees_for_workspace(ws, *_load(ws), depth=3).stats["cache"] == "reused"
