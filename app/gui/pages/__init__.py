"""The wizard's pages, one module per step of :data:`app.gui.stages.STEPS` on the common
:class:`~app.gui.pages.page.StepPage` (``page.py``, with the helpers pages share); ``PAGES`` maps
each step to its page."""
from app.gui.pages.calibrate_camera import CameraPage
from app.gui.pages.calibrate_lights import LightsPage
from app.gui.pages.devices import DevicesPage
from app.gui.pages.fit import FitPage
from app.gui.pages.input import InputPage
from app.gui.pages.reconstruct import ReconstructPage
from app.gui.pages.results import ResultsPage
from app.gui.pages.sweep import SweepPage
from app.gui.pages.texture import TexturePage

PAGES = {"devices": DevicesPage, "calibrate_camera": CameraPage, "calibrate_lights": LightsPage, "sweep": SweepPage,
         "reconstruct": ReconstructPage, "input": InputPage, "fit": FitPage, "texture": TexturePage,
         "results": ResultsPage}
