"""The distribution: one import package, ``reflab``, holding every layer (docs/install.md)."""
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_a_wheel_installs_one_top_level_package_with_every_module(tmp_path):
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                          "-w", str(tmp_path), str(ROOT)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    wheel = next(tmp_path.glob("reflab-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    import reflab

    assert {n.split("/")[0] for n in names} == {"reflab", f"reflab-{reflab.__version__}.dist-info"}
    # Every module of every layer is in it, under reflab/, and the report's template too.
    layers = ("core", "hardware", "calibration", "reconstruction", "inverse", "app")
    modules = {f"reflab/{p.relative_to(ROOT).as_posix()}" for layer in layers for p in (ROOT / layer).rglob("*.py")}
    assert modules <= set(names), sorted(modules - set(names))[:5]
    assert "reflab/__init__.py" in names and "reflab/app/report/templates/report.html.j2" in names
    assert not any(n.startswith("reflab/tests/") or n.startswith("reflab/docs/") for n in names)


def test_version_and_the_public_api_load_lazily():
    code = ("import sys, reflab; assert 'reflab.inverse.stages' not in sys.modules; "
            "print(reflab.__version__, reflab.fit.__module__, reflab.FitOptions.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(ROOT.parent))
    assert out.returncode == 0, out.stderr
    version, module, name = out.stdout.split()
    assert module == "reflab.inverse.stages" and name == "FitOptions"
    assert version == next(line.split('"')[1] for line in (ROOT / "pyproject.toml").read_text().splitlines()
                           if line.startswith("version ="))
