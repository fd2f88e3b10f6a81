"""The repository's folders install as one import package, ``reflab`` (pyproject.toml holds the rest).

The folders keep the names of the design's layers (app, calibration, ...) at the top of the
repository; the mapping below installs them as ``reflab.app``, ``reflab.calibration``, ...
"""
from setuptools import find_packages, setup

LAYERS = ["core", "hardware", "calibration", "reconstruction", "inverse", "app"]
PACKAGES = find_packages(include=[f"{layer}*" for layer in LAYERS])

setup(package_dir={"reflab": "."}, packages=["reflab"] + [f"reflab.{p}" for p in PACKAGES])
