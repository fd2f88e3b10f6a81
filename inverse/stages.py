"""The inverse stages as library functions: options in, a typed result out, a Task for progress.

- :func:`fit` writes fit.json (non-Lambertian parameters of every surface; :mod:`reflab.inverse.fit.rounds`);
- :func:`texture` writes textures/ (per-texel diffuse albedo; :mod:`reflab.inverse.texture.solve`);
- :func:`render` renders the workspace's model (fit.json + textures/ when present, else
  scene.json) to an image; :func:`render_workspace` is the same without writing.

The CLI (``reflab fit | texture | render``), the GUI and the demo call these. Each checks its
:class:`reflab.core.task.Task` inside its long loops (tree levels, fit iterations, texture CG) and
writes its files only after its last check: a cancelled stage leaves nothing half-written.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.core.options import float_list, nonneg_float, nonneg_int, opt, positive_float, positive_int
from reflab.core.task import Task, ensure


# ---------------------------------------------------------------------- fit
@dataclass
class FitOptions:
    """Options of :func:`fit` (``reflab fit``'s flags; docs/fit.md)."""

    workspace: Path
    method: str = opt("ftbo", "ftbo: factorized (faster); nftbo: all parameters by conjugate gradient",
                      choices=["ftbo", "nftbo"])
    depth: int = opt(3, "maximum internal nodes per path of the forward model", type=positive_int)
    saturation: float | None = opt(None, "pixel value at which the camera clips (default: detect a clipped plateau)",
                                   type=positive_float)
    max_iterations: int | None = opt(None, "cap on outer iterations (default: 100 for ftbo, 5000 for nftbo)",
                                     type=positive_int)
    max_seconds: float | None = opt(None, "wall-clock budget of the fit (trees excluded); it stops at the next "
                                          "iteration and fit.json's message says so (default: none)", unit="s",
                                    type=positive_float)
    texture_rounds: int = opt(2, "when a surface is textured: rounds of refitting against the texture recovered "
                                 "from the pixels that directly seen texture lights, at least (over several photographs more, up to 4, while a "
                                 "textured lobe still moves by more than 5 %; 0 = the homogeneous fit alone, "
                                 "as in the dissertation)", type=nonneg_int)
    single: bool = opt(False, "fit the reference photograph alone, ignoring inputs/ (the dissertation's method)",
                       flag="--single-photograph")
    pixels: int = opt(85_000, "pixels the fit reads when it samples (above --sample-above, or a photograph above "
                              "2 MP): a pilot, then the pixels that show lobes, reflections and transmissions and "
                              "a share of the rest; a sixth more per further photograph (0 = never sample)",
                      type=nonneg_int)
    sample_above: float = opt(0.2, "the fit reads every usable pixel of the photographs up to this many megapixels "
                                   "(all photographs together) and samples only above (its rows "
                                   "weighed back: docs/fit.md \"Sampling\")", unit="MP", type=nonneg_float)


@dataclass
class FitResult:
    """What :func:`fit` wrote: fit.json's ``report``, the numeric fit (``reflab.inverse.fit.rounds.FitSolution``)."""

    path: Path
    report: dict
    fit: object

    @property
    def status(self) -> str:
        """fit.json's status: "ok", "not converged", "texture pending" or "poor fit"."""
        return self.report["status"]

    @property
    def warnings(self) -> list:
        return list(self.report.get("warnings", []))


def fit(options: FitOptions, task: Task | None = None, *, on_round=None) -> FitResult:
    """Fit the non-Lambertian parameters of every surface and write fit.json.

    ``on_round(record)`` is called after each texture round (docs/fit.md). The task is stepped
    per outer iteration; its deadline, when it has one, stops the fit like ``max_seconds``.
    """
    from reflab.core.workspace import Workspace, check_folder
    from reflab.inverse.fit.workspace_fit import fit_workspace
    from reflab.inverse.forward.factorization import one_blas_thread

    task = ensure(task)
    o = options
    check_folder(o.workspace, write=True)  # before any work: missing or read-only, named in one line
    # BLAS on one thread for the whole stage, not only F-TBO's rounds: the colour lobes, the albedo
    # model and the texture rounds' products are as small, and OpenBLAS's spin-waiting threads
    # made them several times slower on the loaded two-core machine (docs/fit.md, "Speed").
    report, result = one_blas_thread(fit_workspace)(o.workspace, o.method, o.depth, saturation=o.saturation,
                                   maxiter=o.max_iterations, max_seconds=o.max_seconds,
                                   texture_rounds=o.texture_rounds, progress=on_round, task=task, single=o.single,
                                   pixels=o.pixels, sample_above=int(round(o.sample_above * 1e6)))
    return FitResult(Workspace(o.workspace).fit, report, result)


# ---------------------------------------------------------------------- texture
@dataclass
class TextureOptions:
    """Options of :func:`texture` (``reflab texture``'s flags; docs/texture.md).

    ``depth`` defaults to fit.json's, else 3. The solver's own knobs (tolerance, iteration cap,
    coverage) keep :class:`reflab.inverse.texture.solve.SolverOptions`' defaults.
    """

    workspace: Path
    depth: int | None = opt(None, "maximum internal nodes per path of the forward model (default: fit.json's, else 3)",
                            type=positive_int)
    texel_scale: float = opt(1.0, "texel size as a multiple of the pixel footprint on each surface",
                             type=positive_float)
    texel_size: float | None = opt(None, "texel size for every surface (overrides --texel-scale)", unit="m",
                                   type=positive_float)
    prior: float = opt(1e-3, "relative weight of the pull toward each surface's homogeneous kd", type=nonneg_float)
    smoothness: float = opt(0.01, "relative weight of neighbouring-texel smoothness", type=nonneg_float)
    saturation: float | None = opt(None, "pixel value at which the camera clips (default: detect a clipped plateau)",
                                   type=positive_float)
    max_albedo: float = opt(1.0, "upper bound of kd", type=positive_float)
    single: bool = opt(False, "use the reference photograph alone, ignoring inputs/", flag="--single-photograph")
    tile_pixels: int = opt(1 << 19, "a photograph larger than this is textured this many pixels at a time, in two "
                                    "tiles of half as many reduced at once (their trees built, reduced and released "
                                    "per tile, not cached): bounds memory",
                           type=positive_int)


@dataclass
class TextureResult:
    """What :func:`texture` wrote (``written``: every file in textures/) and the solve
    (``result``: :class:`reflab.inverse.texture.solve.TextureSolution`)."""

    folder: Path
    written: list
    result: object
    materials_source: str
    depth: int
    solver: object  # the reflab.inverse.texture.solve.SolverOptions used
    trees: dict = field(default_factory=dict)  # the trees' stats (``cache``: "reused" or "built", ``build_s``)


def _inputs(ws, camera=None, lights=None):
    """(Camera, Lights, Scene) of the workspace, or from other camera/lights files."""
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.reconstruction.scene import Scene

    camera = Camera.load(camera or ws.require(ws.camera, "reflab calibrate camera"))
    lights = Lights.load(lights or ws.require(ws.lights, "reflab calibrate lights"))
    scene = Scene.load(ws.require(ws.scene, "reflab reconstruct"))
    return camera, lights, scene


def texture(options: TextureOptions, task: Task | None = None, *, log=None) -> TextureResult:
    """Recover the diffuse texture of every surface point the input sees and write textures/.

    ``log`` is told whether the trees were built or reused from the workspace's cache.
    """
    from reflab.core.workspace import Workspace, check_folder, read_json
    from reflab.inverse.fit.photograph import stack_photographs
    from reflab.inverse.forward.photographs import load_photographs
    from reflab.inverse.forward.rendering import undetermined_pixels
    from reflab.inverse.texture import solve as tex
    from reflab.reconstruction.scene import Scene

    task = ensure(task)
    o = options
    ws = Workspace(check_folder(o.workspace, write=True))
    ws.require(ws.camera, "reflab calibrate camera")
    ws.require(ws.lights, "reflab calibrate lights")
    scene = Scene.load(ws.require(ws.scene, "reflab reconstruct"))
    materials, source = tex.load_materials(ws, scene)
    depth = o.depth
    if depth is None:
        depth = int(read_json(ws.fit).get("depth", 3)) if ws.fit.exists() else 3
    solver = tex.SolverOptions(texel_scale=o.texel_scale, texel_size=o.texel_size, prior=o.prior,
                                smoothness=o.smoothness, saturation=o.saturation, bounds=(0.0, o.max_albedo))
    solver.validate()
    photos = load_photographs(ws, reference_only=o.single)
    if max(p.camera.width * p.camera.height for p in photos) > o.tile_pixels:
        from reflab.core.pages import without_huge_pages

        with without_huge_pages():  # many large temporaries: ordinary pages cost less here
            return _texture_tiled(ws, scene, photos, materials, source, depth, solver, o, task, log)
    # Every photograph adds rows to one system (one albedo per texel), the reference alone with
    # ``single``; the solver finds each photograph's saturated pixels in the stacked image.
    stack, image, _, photos = stack_photographs(ws, scene, depth, saturation=o.saturation, single=o.single,
                                                     task=task, log=log)
    trees, intensities = stack.trees, stack.intensities
    padding = None if stack.valid is None else ~stack.valid  # right of a narrower photograph
    # Pixels whose light rests on what the fit left undetermined (a textured surface's own lobe,
    # seen once) or knows only loosely (the ground seen through a sheet whose t is ± 20 %): the
    # texels they make are flagged guessed, and renders that use them say so.
    u = tex.load_uncertainty(ws, scene)
    guess = undetermined_pixels(trees, materials, intensities, u.undetermined, image=image, sigma=u.sigma,
                                noise=u.noise, textured=[s.textured for s in scene]).ravel() \
        if any(u.undetermined) or any(u.sigma) else None
    result = tex.recover_texture(scene, trees, materials, intensities, image, solver, guess=guess, task=task,
                                 exclude=padding)
    photographs = [{"name": p.name, "width": b.width, "height": b.height, "lamps": b.lights}
                   for p, b in zip(photos, stack.blocks)]
    return _write_texture(ws, scene, result, source, depth, solver, trees.stats, photographs, guess, task)


def _texture_tiled(ws, scene, photos, materials, source, depth, solver, o, task, log) -> TextureResult:
    """:func:`texture` for photographs larger than ``tile_pixels``: tile by tile
    (:mod:`reflab.inverse.texture.tiles`), the same texture within float rounding."""
    from reflab.core.images import read_image
    from reflab.core.workspace import WorkspaceError
    from reflab.inverse.fit.photograph import check_image, saturated_pixels
    from reflab.inverse.texture import solve as tex
    from reflab.inverse.texture.tiles import texture_tiled

    images = []
    for p in photos:
        img = check_image(read_image(p.image), p.camera.width, p.camera.height, p.image)
        if saturated_pixels(img, o.saturation).all():
            raise WorkspaceError(p.image, "pixels", "some pixels below the saturation level",
                                 got="every pixel saturated")
        images.append(img)
    result, info = texture_tiled(scene, photos, images, materials, solver, depth=depth, tile_pixels=o.tile_pixels,
                                 uncertainty=tex.load_uncertainty(ws, scene), task=task, log=log)
    del images
    photographs = [{"name": p.name, "width": w, "height": h, "lamps": len(p.lights)}
                   for p, (_, w, h) in zip(photos, info["blocks"])]
    return _write_texture(ws, scene, result, source, depth, solver, info["trees"], photographs, info["guess"], task)


def _write_texture(ws, scene, result, source, depth, solver, trees_stats, photographs, guess, task) -> TextureResult:
    """textures/ and its index.json with the stage's figures, after the last check."""
    from reflab.inverse.texture import solve as tex

    extra = {"materials": source, "depth": depth, "trees_s": trees_stats.get("build_s"),
             "photographs": photographs,
             "undetermined_pixels": int(np.count_nonzero(guess)) if guess is not None else 0,
             "options": {"texel_scale": solver.texel_scale, "texel_size": solver.texel_size, "prior": solver.prior,
                         "smoothness": solver.smoothness, "saturation": solver.saturation,
                         "bounds": list(solver.bounds), "min_coverage": solver.min_coverage,
                         "amplification_limit": solver.amplification_limit}}
    if trees_stats.get("cache") == "tiled":
        extra["tiles"] = {"count": trees_stats["tiles"], "pixels": trees_stats["tile_pixels"]}
    task.check()
    written = tex.write_textures(ws, scene, result, extra)
    task.step(1, 1, f"wrote {len(written)} files in {ws.textures}")
    return TextureResult(ws.textures, written, result, source, depth, solver, trees_stats)


# ---------------------------------------------------------------------- plan
@dataclass
class PlanOptions:
    """Options of :func:`plan` (``reflab plan``'s flags; docs/fit.md "Plan")."""

    workspace: Path
    max_shots: int = opt(3, "shots to plan at most", type=positive_int)
    angles: tuple = opt(tuple(range(-165, 181, 15)), "turntable angles to consider, from the input's view",
                        unit="deg", type=float_list)
    turntable_centre: tuple | None = opt(None, "where the turntable axis meets the ground, x,y (default: from the "
                                               "sweep reconstruct registered)", unit="m", type=float_list,
                                         metavar="X,Y")
    reduce: int = opt(4, "candidate views are ray-cast at 1/REDUCE of the camera's size", type=positive_int)


@dataclass
class PlanResult:
    """What :func:`plan` wrote: plan.json and the shots in order (:class:`reflab.inverse.plan.Shot`)."""

    path: Path
    shots: list
    report: dict


def plan(options: PlanOptions, task: Task | None = None, *, log=None) -> PlanResult:
    """Choose the further photographs that would most reduce the σ of what the fit left
    undetermined or loose (:mod:`reflab.inverse.plan`) and write plan.json."""
    from reflab.core.workspace import OptionError, Workspace, check_folder, read_json, write_json
    from reflab.inverse.fit.photograph import stack_photographs
    from reflab.inverse.forward.photographs import taken_shots
    from reflab.inverse.plan import plan_shots, reported_relative_sigma
    from reflab.inverse.texture import solve as tex
    from reflab.reconstruction.scene import Scene

    task = ensure(task)
    o = options
    ws = Workspace(check_folder(o.workspace, write=True))
    if int(o.max_shots) < 1:
        raise OptionError("max_shots", f"must be at least 1, got {o.max_shots}")
    if int(o.reduce) < 1:
        raise OptionError("reduce", f"must be at least 1, got {o.reduce}")
    scene = Scene.load(ws.require(ws.scene, "reflab reconstruct"))
    fit_report = read_json(ws.require(ws.fit, "reflab fit"))
    depth = int(fit_report.get("depth", 3))
    materials, _ = tex.load_materials(ws, scene)
    if o.turntable_centre is not None:
        centre = np.asarray(o.turntable_centre, dtype=float).ravel()
        if centre.shape != (2,) or not np.all(np.isfinite(centre)):
            raise OptionError("turntable_centre", f"expected X,Y in metres, got {o.turntable_centre!r}")
        direction = 1.0
    else:
        from reflab.reconstruction.stages import turntable_axis

        centre, direction = turntable_axis(ws)
    stack, _, _, photos = stack_photographs(ws, scene, depth, task=task, log=log)
    noise = np.asarray(fit_report.get("noise") or [0.0] * 3, dtype=float)
    peak = float((fit_report.get("image") or {}).get("peak") or 1.0)
    noise = np.maximum(noise, 1e-3 * peak)  # a noise-free photograph plans as if it had 0.1 % noise
    result = plan_shots(stack, scene, materials, noise, n_lamps=len(photos[0].lights), lights=photos[0].lights,
                        camera=photos[0].camera, centre=centre, direction=direction, angles=o.angles,
                        taken=taken_shots(photos), max_shots=int(o.max_shots), reduce=int(o.reduce), depth=depth,
                        held=[s.material.given for s in scene], reported=reported_relative_sigma(fit_report),
                        lobe_shapes=fit_report.get("lobe_shapes"), task=task, log=log)
    report = dict(result.report, turntable={"centre": [float(v) for v in centre], "direction": direction},
                  photographs=[p.name for p in photos])
    task.check()
    write_json(ws.plan, report)
    return PlanResult(ws.plan, result.shots, report)


# ---------------------------------------------------------------------- render
@dataclass
class RenderOptions:
    """Options of :func:`render`: another ``camera``/``lights`` file gives a novel view or a
    relighting; ``aov="albedo"`` renders kd of the surface seen at each pixel; ``output``
    defaults to WORKSPACE/render.exr (albedo.exr for the AOV)."""

    workspace: Path
    output: Path | None = opt(None, "output image (.exr, .png or .tif); default WORKSPACE/render.exr",
                              flag=("-o", "--output"), type=str)
    camera: Path | None = opt(None, "the camera to render from: a camera.json (a novel view); default the "
                                    "workspace's", type=str, metavar="CAMERA.json")
    lights: Path | None = opt(None, "lights.json to light with (relighting); default the workspace's", type=str,
                              metavar="LIGHTS.json")
    aov: str | None = opt(None, "write the kd of the surface seen at each pixel instead", choices=["albedo"])
    depth: int = opt(3, "maximum internal nodes per path of the forward model", type=positive_int)
    tile_pixels: int = opt(1 << 19, "an image larger than this is rendered a tile of this many pixels at a time "
                                    "(its trees built and released per tile, not cached): bounds memory",
                           type=positive_int)


@dataclass
class RenderResult:
    """What :func:`render` wrote: the image, its 8-bit preview, :func:`render_workspace`'s info, and
    the mask of pixels whose value rests on undetermined parameters (None when there are none)."""

    path: Path
    preview: Path
    image: np.ndarray
    info: dict = field(default_factory=dict)
    undetermined: Path | None = None


def render_workspace(workspace, camera=None, lights=None, *, aov: str | None = None, depth: int = 3,
                     task: Task | None = None, log=None, tile_pixels: int = 1 << 19) -> tuple:
    """Render the model of ``workspace`` (see the module's description); writes nothing.

    Parameters
    ----------
    workspace : path-like
    camera, lights : path-like, optional
        Other camera.json / lights.json files (novel view, relighting).
    aov : {None, "albedo"}
        None: linear radiance; "albedo": kd of the surface seen at each pixel, NaN where unknown.
    depth : int
        Maximum internal nodes per path.
    task : Task, optional
    log : callable, optional
        Told whether the trees were built or reused from the workspace's cache.
    tile_pixels : int
        An image of more pixels is rendered a tile of rows at a time (:func:`_render_tiled`: the
        same image, memory bounded; its trees are not cached and ``info["trees"]`` is None).

    Returns
    -------
    image : (H, W, 3) float64 ndarray
    info : dict
        ``materials`` (source file), ``texture_nodes`` (nodes with recovered albedo, or None),
        ``unknown_albedo`` (nodes whose albedo was unknown), ``unknown_pixels`` ((H, W) bool: a
        node of the pixel's tree had unknown albedo, so the homogeneous kd stood in),
        ``undetermined_pixels`` ((H, W) bool: the pixel's predicted light rests on parameters fit.json
        calls undetermined, on determined ones whose σ leaves it loose, or on texels the texture
        stage flagged guessed,
        :func:`reflab.inverse.forward.rendering.undetermined_pixels`; all False for the albedo AOV), ``trees_s``,
        ``render_s``, ``trees``, ``nodes``.
    """
    from reflab.core.workspace import Workspace
    from reflab.inverse.forward.rendering import render as render_trees, render_albedo, undetermined_pixels
    from reflab.inverse.texture.solve import albedo_nodes, guessed_nodes, load_materials, load_texture_maps, load_uncertainty
    from reflab.inverse.forward.trees import trees_for_workspace

    task = ensure(task)
    ws = Workspace(workspace)
    cam, lig, scene = _inputs(ws, camera, lights)
    materials, source = load_materials(ws, scene)
    if cam.width * cam.height > tile_pixels:
        return _render_tiled(ws, scene, cam, lig, materials, source, aov, depth, tile_pixels, task, log)

    t0 = time.perf_counter()
    trees = trees_for_workspace(ws, scene, cam, lig, depth=depth, log=log, task=task)
    t1 = time.perf_counter()
    textures = load_texture_maps(ws, scene) if ws.textures.is_dir() else None  # read once: albedo and guesses
    kd_nodes = albedo_nodes(ws, scene, trees, textures) if textures is not None else None
    info = {"materials": source, "texture_nodes": None, "unknown_albedo": 0,
            "unknown_pixels": np.zeros((cam.height, cam.width), dtype=bool)}
    if kd_nodes is not None:
        unknown = ~np.all(np.isfinite(kd_nodes), axis=1)
        info["texture_nodes"] = int(np.count_nonzero(~unknown))
        info["unknown_albedo"] = int(np.count_nonzero(unknown))
        info["unknown_pixels"] = (np.bincount(trees.pixel[unknown], minlength=cam.width * cam.height) > 0).reshape(cam.height, cam.width)
    task.check()
    if aov == "albedo":
        image = render_albedo(trees, materials, kd_nodes)
    else:
        if kd_nodes is not None:
            # Points the texture stage never saw keep the surface's homogeneous kd.
            homogeneous = np.array([m["kd"] for m in materials])[trees.surface]
            kd_nodes = np.where(np.isfinite(kd_nodes), kd_nodes, homogeneous)
        image = render_trees(trees, materials, lig.intensities, kd_nodes=kd_nodes)
    info["undetermined_pixels"] = np.zeros((cam.height, cam.width), dtype=bool)
    if aov is None:
        u = load_uncertainty(ws, scene)
        guessed = guessed_nodes(ws, scene, trees, textures) if textures is not None else None
        if any(u.undetermined) or any(u.sigma) or (guessed is not None and guessed.any()):
            info["undetermined_pixels"] = undetermined_pixels(trees, materials, lig.intensities, u.undetermined,
                                                              kd_nodes=kd_nodes, guessed=guessed, sigma=u.sigma,
                                                              noise=u.noise, textured=[s.textured for s in scene])
    info.update(trees_s=t1 - t0, render_s=time.perf_counter() - t1, trees=trees, nodes=len(trees))
    return image, info


def _render_tiled(ws, scene, cam, lig, materials, source, aov, depth, tile_pixels, task, log) -> tuple:
    """:func:`render_workspace` a tile of rows at a time: each tile's trees built, rendered and
    released (not cached). Every pixel is its own tree's, so the image is the untiled one; what
    needs the whole view (its peak, for the undetermined pixels) is decided after the last tile."""
    from reflab.inverse.forward.rendering import (release_basis, render as render_trees, render_albedo,
                                                  undetermined_decision, undetermined_part)
    from reflab.inverse.forward.trees import TileTask, build_trees, tile_rows
    from reflab.inverse.texture.solve import (albedo_nodes, guessed_flags, guessed_nodes, load_texture_maps,
                                              load_uncertainty)

    t0 = time.perf_counter()
    H, W = cam.height, cam.width
    textures = load_texture_maps(ws, scene) if ws.textures.is_dir() else None
    flags = guessed_flags(ws, scene, textures) if textures is not None and aov is None else None  # read once
    u = load_uncertainty(ws, scene) if aov is None else None
    loose = u is not None and (any(u.undetermined) or any(u.sigma))
    textured = [s.textured for s in scene]
    homogeneous = np.array([m["kd"] for m in materials])
    image = np.empty((H, W, 3))
    unknown_pixels = np.zeros((H, W), dtype=bool)
    part, any_part = None, False
    texture_nodes = unknown_albedo = nodes = 0
    trees_s = 0.0
    tiles = tile_rows(H, W, tile_pixels)
    for k, (r0, r1) in enumerate(tiles):
        label = f"render: tile {k + 1} of {len(tiles)}"
        task.step(k, len(tiles), f"{label} (rows {r0}–{r1 - 1})")
        t = time.perf_counter()
        trees = build_trees(scene, cam, lig, depth, task=TileTask(task, k, len(tiles), label), rows=(r0, r1))
        trees_s += time.perf_counter() - t
        nodes += len(trees)
        kd_nodes = albedo_nodes(ws, scene, trees, textures) if textures is not None else None
        if kd_nodes is not None:
            unknown = ~np.all(np.isfinite(kd_nodes), axis=1)
            texture_nodes += int(np.count_nonzero(~unknown))
            unknown_albedo += int(np.count_nonzero(unknown))
            unknown_pixels[r0:r1] = (np.bincount(trees.pixel[unknown], minlength=trees.width * trees.height) > 0
                                     ).reshape(r1 - r0, W)
        task.check()
        if aov == "albedo":
            image[r0:r1] = render_albedo(trees, materials, kd_nodes)
            continue
        if kd_nodes is not None:
            kd_nodes = np.where(np.isfinite(kd_nodes), kd_nodes, homogeneous[trees.surface])
        image[r0:r1] = render_trees(trees, materials, lig.intensities, kd_nodes=kd_nodes)
        guessed = guessed_nodes(ws, scene, trees, textures, flags) if textures is not None else None
        if loose or (guessed is not None and guessed.any()):
            if part is None:
                part = np.zeros((H, W, 3))
            any_part = True
            part[r0:r1] = undetermined_part(trees, materials, lig.intensities, u.undetermined, kd_nodes=kd_nodes,
                                            guessed=guessed, sigma=u.sigma, textured=textured)
        del trees, kd_nodes
        release_basis()
    undetermined = np.zeros((H, W), dtype=bool)
    if any_part:
        undetermined = undetermined_decision(part, image, float(image.max()) if image.size else 0.0, noise=u.noise)
    if log is not None:
        log(f"trees: built in {len(tiles)} tiles of up to {tile_pixels} pixels, {trees_s:.2f} s ({nodes} nodes), "
            "not cached")
    info = {"materials": source, "texture_nodes": texture_nodes if textures is not None else None,
            "unknown_albedo": unknown_albedo, "unknown_pixels": unknown_pixels, "undetermined_pixels": undetermined,
            "trees_s": trees_s, "render_s": time.perf_counter() - t0 - trees_s, "trees": None, "nodes": nodes,
            "tiles": len(tiles)}
    return image, info


def render(options: RenderOptions, task: Task | None = None, *, log=None) -> RenderResult:
    """Render the workspace's model and write the image and an 8-bit PNG preview beside it."""
    from reflab.core.images import write_image, write_preview
    from reflab.core.workspace import Workspace, check_folder

    task = ensure(task)
    o = options
    out = Path(o.output) if o.output else Workspace(check_folder(o.workspace)).render(o.aov)
    check_folder(out.parent, write=True, create=True, what="output folder")  # a read-only workspace renders elsewhere
    image, info = render_workspace(o.workspace, o.camera, o.lights, aov=o.aov, depth=o.depth, task=task, log=log,
                                   tile_pixels=o.tile_pixels)
    task.check()
    write_image(out, image, allow_nan=o.aov == "albedo")
    preview = out.with_suffix(".png") if out.suffix.lower() != ".png" else out.with_name(out.stem + "_preview.png")
    preview = write_preview(preview, image, exposure=1.0 if o.aov == "albedo" else None)
    guess = None
    if info["undetermined_pixels"].any():  # where the render is a guess, as a picture beside it
        guess = write_image(out.with_name(out.stem + "_undetermined.png"),
                            info["undetermined_pixels"].astype(np.float32))
    task.step(1, 1, f"wrote {out}")
    return RenderResult(out, preview, image, info, guess)
