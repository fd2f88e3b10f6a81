"""`reflab demo WORKSPACE`: the simulated lab end to end, from its captures, through the step list.

1. writes the truth (app/demo_score.py: WORKSPACE/truth/, docs/formats.md "The simulated lab's
   truth"), which no stage reads;
2. opens the simulated board and camera (``reflab.app.devices.Devices("sim", "sim")``) and runs app/steps.py's
   ``STEPS`` in order, the functions the GUI runs: devices -> calibrate camera (target shots) ->
   calibrate lights (rod shots) -> sweep (then the simulated user marks the mirror's and the
   sheet's corners and names the surfaces, as a person does in the GUI) -> reconstruct -> input
   photograph -> fit -> [plan -> the planned further photographs -> fit, while the plan expects a
   shot to fix what is still open] -> photographs for the texture's detail (full resolution, near
   the input's view) -> texture -> results; then the results step again for the
   novel and the relit view (truth/'s camera and lamps), and the report;
3. after each stage prints its error against the truth and its time, and at the end a table.

The options (:func:`step_options`, :func:`views`) are those README's stepwise commands give by
hand ("The simulated lab step by step"); tests/test_demo_chain.py checks that they agree and runs
the commands. Exit status as the commands': 1 on a device fault, 130 when a capture is
interrupted, 3 when the fit is poor, 2 for a bad file or option (app/cli.py).
"""
from __future__ import annotations

import time
from pathlib import Path

from reflab.app.console import LOG, running
from reflab.app.devices import SIM_SIZE

#: The simulated camera's image size (``--size``'s default) and the turntable axis (x, y), metres.
SIZE, CENTRE = SIM_SIZE, (0.0, 0.0)

#: Photographs for the texture's detail, taken after the last fit: at this many times the
#: calibrated size (a camera's full resolution; the lab's 2-8 mm print grain is finer than twice
#: the reference photograph's 1.45 mm ground pixels) from the input's view and the turntable turned
#: by these angles (degrees), every lamp on: views close to the input's, whose small turns the
#: reconstructed axis registers to a fraction of the grain (docs/fit.md, "Where the demo's error
#: lives"). The texels follow their footprint, smoothed against what registration leaves.
DETAIL_SCALE, DETAIL_ANGLES, SMOOTHNESS = 2, (0.0, 30.0, -30.0), 0.1


def step_options(quick: bool = False, size=SIZE) -> dict[str, dict]:
    """Options per step on the simulated lab: its props' target, rod and grey card (the region
    5 mm inside the card's edges), the turntable axis; sweep shots and texture rounds (--quick:
    24 and 1); "detail": the photographs taken for the texture after the last fit (their turntable
    angles and size, :data:`DETAIL_SCALE` times ``size``), and the texture's texels at their footprint."""
    from reflab.hardware.sim.props import LabProps

    props, inset = LabProps(), 0.005
    x0, x1, y0, y1 = props.card
    region = [round(v, 6) for v in (x0 + inset, x1 - inset, y0 + inset, y1 - inset)]
    return {"calibrate_camera": {"grid": props.grid, "spacing": props.spacing},
            "calibrate_lights": {"rod_height": props.rod_height, "sheet_reflectance": props.card_reflectance,
                                 "sheet_region": region},
            "sweep": {"count": 24 if quick else 36}, "reconstruct": {"turntable_centre": CENTRE},
            "fit": {"texture_rounds": 1 if quick else 2},
            "detail": {"angles": list(DETAIL_ANGLES), "size": (DETAIL_SCALE * size[0], DETAIL_SCALE * size[1])},
            "texture": {"texel_scale": 1 / DETAIL_SCALE, "smoothness": SMOOTHNESS}}


def views(workspace) -> dict[str, dict]:
    """The results step's options for the novel and the relit view: truth/'s camera or lamps."""
    from reflab.core.workspace import Workspace

    ws = Workspace(workspace)
    truth = Workspace(ws.truth)
    return {"novel": {"camera": truth.view("novel")[0], "output": ws.view("novel")[1]},
            "relit": {"lights": truth.view("relit")[0], "output": ws.view("relit")[1]}}


def _log(line: str) -> None:
    LOG.info(line)


def _run_steps(root: Path, truth: dict, size, quick: bool, rows: list, further: int = 2) -> int:
    """Every step and the two views on the simulated rig; a row (stage, seconds, error) per stage."""
    from reflab.app import demo_score as score, steps
    from reflab.app.devices import Devices, SimOptions
    from reflab.hardware.sim.user import mark_sweep

    options = step_options(quick, size)
    runs = [(s.name.replace("_", " "), s, options.get(s.name, {})) for s in steps.STEPS]
    runs += [(f"render {view}", steps.step("results"), opts) for view, opts in views(root).items()]
    with Devices("sim", "sim", sim=SimOptions(size=size, centre=list(CENTRE)), log=_log) as rig:
        for stage, step, opts in runs:
            if step.name == "texture" and options.get("detail"):
                _detail_photographs(root, rig, options["detail"], rows)
            _log(f"[demo] step {step.name}: {step.title}")
            t0 = time.perf_counter()
            with running(f"demo {stage}") as task:  # a progress bar; Ctrl-C cancels the step
                result = step.run(root, task, rig=rig, log=_log, **opts)
            if step.name == "sweep":  # what a person marks in the GUI after the sweep
                path = mark_sweep(root, rig.camera.sim_lab, result.capture.manifest, centre=CENTRE)
                _log(f"[demo] the simulated user marked the mirror's and the sheet's corners and named the surfaces "
                     f"in {path}")
            seconds = time.perf_counter() - t0
            _log(f"[demo] step {step.name}: {result.summary}")
            if step.name == "fit" and result.value.status == "poor fit":  # `reflab fit`'s exit status
                _log(f"[demo] stage {stage} failed (exit 3) after {seconds:.1f} s: later stages skipped")
                return 3
            rows.append((stage, seconds, score.score_stage(stage, root, truth)))
            _log(f"[demo] {stage}: {seconds:.1f} s{'; ' + rows[-1][2] if rows[-1][2] else ''}")
            if step.name == "fit" and further:
                code = _further_photographs(root, rig, options, truth, rows, further)
                if code:
                    return code
    return 0


def _detail_photographs(root: Path, rig, detail: dict, rows: list) -> None:
    """The photographs for the texture's detail (``detail``: turntable angles and size), every
    lamp on, into inputs/ as the GUI's input step and ``reflab capture inputs --angles A,.. --size WxH`` take them."""
    from reflab.app import steps

    t0 = time.perf_counter()
    r = steps.detail_photographs(root, rig, angles=detail["angles"], size=detail["size"], log=_log)
    _log(f"[demo] step detail: {r.summary}")
    rows.append(("detail photos", time.perf_counter() - t0, ""))


def _further_photographs(root: Path, rig, options: dict, truth: dict, rows: list, rounds: int) -> int:
    """Plan -> take the planned shots -> fit again (``options["fit"]``), until the plan expects no
    shot to gain enough (every parameter the photographs show determined, or none that the rig's
    shots would fix)."""
    from reflab.app import demo_score as score, steps
    from reflab.core.workspace import Workspace, read_json
    from reflab.inverse.plan import why

    ws = Workspace(root)
    for n in range(1, rounds + 1):
        t0 = time.perf_counter()
        _log(f"[demo] further photographs, round {n}: plan the shots that would fix what the fit left open")
        result = steps.further_photographs(root, rig, log=_log)
        plan = read_json(ws.plan)
        if not result.value:
            _log(f"[demo] round {n}: no further shot would gain enough; still open: "
                 f"{', '.join(plan.get('left_open', [])) or 'nothing'}")
            break
        for shot in plan["shots"]:
            _log(f"[demo] took {shot['name']} (turntable {shot['angle_deg']:g} deg, lamps {shot['lamps']}) because it "
                 f"determines {why(shot)}")
        r = steps.step("fit").run(root, rig=rig, log=_log, **options.get("fit", {}))
        _log(f"[demo] step fit: {r.summary}")
        if r.value.status == "poor fit":
            _log("[demo] stage fit failed (exit 3) over the further photographs: later stages skipped")
            return 3
        stage = f"fit +{len(read_json(ws.fit).get('photographs', [])) - 1} photos"
        rows.append((stage, time.perf_counter() - t0, score.score_stage("fit", root, truth)))
        _log(f"[demo] {stage}: {rows[-1][1]:.1f} s{'; ' + rows[-1][2] if rows[-1][2] else ''}")
    return 0


def run_lab(args) -> int:
    from reflab.app import demo_score as score
    from reflab.app.report.build import build_report
    from reflab.app.report.data import summary_text
    from reflab.hardware.cameras import CameraError
    from reflab.hardware.capture import CaptureCancelled, CaptureError
    from reflab.hardware.grbl import GrblError
    from reflab.core.workspace import OptionError, Workspace, read_json, write_json

    root, size = Path(args.workspace), args.size or SIZE
    camera = Workspace(root).camera
    if camera.exists():  # a re-run keeps finished captures: they must be of the size scored against
        earlier = read_json(camera)
        if [earlier.get("width"), earlier.get("height")] != list(size):
            raise OptionError("size", f"{root} holds a demo at {earlier.get('width')}x{earlier.get('height')} "
                                      f"({camera.name}); give that size or another folder, not {size[0]}x{size[1]}")
    start = t0 = time.perf_counter()
    truth = score.write_truth(root, size, depth=args.depth)
    _log(f"[demo] wrote the truth to {Workspace(root).truth} ({time.perf_counter() - t0:.1f} s)")
    if args.truth_only:
        return 0
    rows = []
    try:  # a bad file or option stops the demo as it stops the CLI (exit 2)
        code = _run_steps(root, truth, size, args.quick, rows, getattr(args, "further_rounds", 2))
    except CaptureCancelled as exc:
        LOG.error(f"reflab demo: {exc}")
        return 130
    except (CaptureError, GrblError, CameraError) as exc:
        LOG.error(f"reflab demo: error: {exc}")
        return 1
    if code:
        return code
    t0 = time.perf_counter()
    html, summary = build_report(root)
    for path, why in summary.get("unreadable", {}).items():
        LOG.warning(f"warning: {path} is unreadable, left out of the report ({why})")
    _log(f"{summary_text(summary)}\nwrote {write_json(Workspace(root).report_json, summary)}\nwrote {html}")
    rows.append(("report", time.perf_counter() - t0, ""))
    _log(f"[demo] report: {rows[-1][1]:.1f} s")
    LOG.info("[demo] stage             time (s)  error against truth/")
    for stage, seconds, error in rows:
        LOG.info(f"[demo] {stage:<17} {seconds:8.1f}  {error}")
    LOG.info(f"[demo] done in {time.perf_counter() - start:.1f} s")
    return 0
