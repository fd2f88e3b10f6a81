"""The texture of a large photograph, a tile of image rows at a time (docs/texture.md, "Large photographs").

A photograph's trees take about 2 KB a pixel (a 12 MP photograph: 25 GB). The texture's system
needs far less of them: per node on a textured surface its pixel, triangle, barycentric point
and two per-band factors (:class:`reflab.inverse.texture.solve.TexturedNodes`, about 90 bytes),
per pixel the light of everything else (``Q``) and, where fit.json leaves parameters
undetermined, whether the pixel's light rests on them. So the trees are built a tile of rows at
a time (:func:`reflab.inverse.forward.trees.build_trees`' ``rows``), reduced to these and
released; peak memory grows with the photograph's pixels and the system's non-zeros, not with the
tree nodes of the whole photograph. The texel size needs each node's footprint, measured against
its right and lower neighbours: a tile is cast with one row more than it keeps.

Each node is cast and reduced exactly as in the whole photograph's trees, and the tiles
concatenate in pixel order, so the system, and the texture, are the untiled ones (tests/test_texture_tiles.py).
Tiled trees are not cached (a 12 MP photograph's would fill 25 GB of disk).
"""
from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from reflab.core.pages import release_free_memory
from reflab.inverse.texture.solve import (SolverOptions, TextureSolution, TexturedNodes, assemble_system,
                                          maps_from_footprints, solve_texture, textured_nodes)
from reflab.inverse.texture.texels import pixel_footprint

#: Tiles reduced at once (threads; Embree's casts and numpy's loops release the GIL), each of
#: ``tile_pixels / TILE_WORKERS`` pixels so that the trees in memory stay about ``tile_pixels``'
#: (two whole tiles took a second tile's trees: +1.2 GB at 12 MP, over the 8 GB bar). Two: the
#: 3 MP tiles in 5.95 and 6.29 s against 8.86 and 8.58 s in one (load 1.8–2.0, back to back;
#: 8 % more CPU time, +0.15 GB); at a load of 10 two whole tiles gained nothing (34.0 and 40.8 s
#: against 37.8 and 33.4 s): a busy machine has no second core to give.
TILE_WORKERS = 2

def texture_tiled(scene, photos, images, materials, solver: SolverOptions, *, depth: int, tile_pixels: int,
                  uncertainty=None, task=None, log=None) -> tuple[TextureSolution, dict]:
    """Recover the texture from ``photos`` (:class:`reflab.inverse.forward.photographs.Photograph`)
    with their checked ``images`` ((h, w, 3) float64 each), tile by tile.

    The photographs stack as :func:`reflab.inverse.forward.photographs.stack_trees` stacks them
    (one tall image, lamps in shared slots); ``uncertainty``
    (:class:`reflab.inverse.texture.solve.Uncertainty`) flags the pixels whose light rests on what
    the fit left undetermined, as the untiled stage does. ``task`` is stepped per tile and per tree
    level, checked every conjugate-gradient iteration; nothing is written.

    Returns
    -------
    result : TextureSolution
    info : dict
        ``trees`` (stats: ``build_s``, ``nodes``, ``tiles``, ``cache`` "tiled"), ``guess`` ((H·W,)
        bool or None), ``blocks`` ((row0, width, height) per photograph), ``width``, ``height``.
    """
    from threadpoolctl import threadpool_limits

    from reflab.inverse.forward.photographs import lamp_slots, slot_lights
    from reflab.inverse.forward.rendering import release_basis, undetermined_decision, undetermined_part
    from reflab.inverse.forward.trees import TileTask, build_trees, tile_rows

    t0 = time.perf_counter()
    width = max(p.camera.width for p in photos)
    blocks, row0 = [], 0
    for p in photos:
        blocks.append((row0, p.camera.width, p.camera.height))
        row0 += p.camera.height
    height, npix = row0, width * row0
    if len(photos) == 1:
        intensities, assign = np.asarray(photos[0].lights.intensities, dtype=np.float64).reshape(-1, 3), None
        image = np.asarray(images[0], dtype=np.float64)
    else:
        intensities, assign = lamp_slots([p.lights for p in photos])
        image = np.zeros((height, width, 3))
        for (r, w, h), img in zip(blocks, images):
            image[r:r + h, :w] = img
    flat = image.reshape(npix, 3)
    padding = None
    if any(w != width for _, w, _ in blocks):
        padding = np.ones((height, width), dtype=bool)
        for r, w, h in blocks:
            padding[r:r + h, :w] = False
        padding = padding.ravel()
    u = uncertainty
    flag = u is not None and (any(u.undetermined) or any(u.sigma))
    guess = np.zeros(npix, dtype=bool) if flag else None
    peak = float(flat.max()) if flat.size else 0.0
    textured = [s for s, surf in enumerate(scene) if surf.textured]
    is_textured = [surf.textured for surf in scene]

    # Pixels in flight stay ``tile_pixels``: each of the workers' tiles a share of them.
    per_tile = max(1, int(tile_pixels) // max(1, TILE_WORKERS))
    tiles = [(i, r0, r1) for i, p in enumerate(photos) for r0, r1 in tile_rows(p.camera.height, p.camera.width, per_tile)]
    Q = np.zeros((npix, 3))

    def reduce_tile(k):
        """Tile ``k``'s trees, reduced: (textured nodes, footprints per surface, nodes, build s);
        its rows of ``Q`` and ``guess`` are written in place (tiles never share a row)."""
        i, r0, r1 = tiles[k]
        p, (b_row0, w, h) = photos[i], blocks[i]
        label = f"texture: tile {k + 1} of {len(tiles)}"
        if task is not None:
            task.check()  # a tile queued behind a cancelled one stops before it says it started
            task.step(k, len(tiles), f"{label} (rows {r0}–{r1 - 1} of {p.name})")
        # One row more than the tile keeps: its last row's footprints need the row below.
        extra = min(r1 + 1, h)
        trees = build_trees(scene, p.camera, p.lights, depth,
                            task=None if task is None else TileTask(task, k, len(tiles), label), rows=(r0, extra))
        if assign is not None:
            trees.light_dir, trees.light_dist2, trees.visible = slot_lights(trees, assign[i], len(intensities))
        own = (r1 - r0) * w
        keep = trees.pixel < own
        fps = {}
        for s in textured:
            sel = np.flatnonzero(trees.surface == s)
            if len(sel) and solver.texel_size is None:
                fps[s] = pixel_footprint(trees.pixel[sel], trees.path[sel], trees.point[sel], w)[keep[sel]]
            elif len(sel):
                fps[s] = np.zeros(int(np.count_nonzero(keep[sel])))
        local = np.arange((extra - r0) * w, dtype=np.int64)
        pixel_map = (local // w + r0 + b_row0) * width + local % w
        nodes, q = textured_nodes(trees, materials, intensities, textured, pixel_map=pixel_map, keep=keep)
        Q[pixel_map[:own]] = q[:own]
        if flag:
            part = undetermined_part(trees, materials, intensities, u.undetermined, textured=is_textured,
                                     sigma=u.sigma).reshape(-1, 3)[:own]
            guess[pixel_map[:own]] = undetermined_decision(part, flat[pixel_map[:own]], peak, noise=u.noise)
        release_basis()
        return nodes, fps, int(np.count_nonzero(keep)), trees.stats["build_s"]

    parts, footprints = [], {s: ([], []) for s in textured}  # surface -> (reference's, further photographs')
    build_s, n_nodes = 0.0, 0
    # With TILE_WORKERS > 1, tiles are reduced that many at a time in threads, taken back in order.
    workers = max(1, min(TILE_WORKERS, len(tiles)))
    pool = ThreadPoolExecutor(workers) if workers > 1 else None
    # BLAS on one thread while the tiles run: their one large product (the camera's rays, (N, 3)
    # @ (3, 3)) took 0.1 s of spin-waiting CPU a tile on two threads at a load of 5, 4 ms on one
    # (the same floats: OpenBLAS splits the rows between its threads).
    blas = threadpool_limits(1, user_api="blas")
    try:
        futures = deque(pool.submit(reduce_tile, k) for k in range(len(tiles))) if pool else None
        for k, (i, _, _) in enumerate(tiles):
            # popleft: the future is dropped, only parts keeps the nodes
            nodes, fps, n_keep, seconds = futures.popleft().result() if pool else reduce_tile(k)
            parts.append(nodes)
            for s, fp in fps.items():
                footprints[s][0 if i == 0 else 1].append(fp)
            n_nodes, build_s = n_nodes + n_keep, build_s + seconds
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)  # a cancel or an error: no further tile starts
            release_free_memory()  # what the workers' heaps kept, before the assembly's peak
        blas.restore_original_limits()
    if task is not None:
        task.step(len(tiles), len(tiles), "texture: the system")
    footprint = {}
    for s, (ref, further) in footprints.items():
        chosen = ref if sum(len(f) for f in ref) else further  # the reference photograph's, when it sees the surface
        if sum(len(f) for f in chosen):
            footprint[s] = np.concatenate(chosen) if solver.texel_size is None else None
    maps = maps_from_footprints(scene, footprint, solver, max(width, height))
    t_maps = time.perf_counter()
    nodes = TexturedNodes.concatenate(parts) if parts else None
    del parts
    system = assemble_system(nodes, Q, flat, materials, maps, solver, padding, release=True)
    del nodes, Q
    result = solve_texture(system, maps, materials, solver, guess=guess, task=task,
                           times=(t0, t_maps, time.perf_counter()))
    stats = {"cache": "tiled", "build_s": build_s, "nodes": n_nodes, "tiles": len(tiles),
             "tile_pixels": per_tile, "workers": workers}
    if log is not None:
        log(f"trees: built in {len(tiles)} tiles of up to {per_tile} pixels ({workers} at a time), {build_s:.2f} s "
            f"({n_nodes} nodes), not cached")
    return result, {"trees": stats, "guess": guess, "blocks": blocks, "width": width, "height": height}
