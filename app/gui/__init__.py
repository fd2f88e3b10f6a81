"""The guided lab GUI (`reflab gui`, INTERFACES.md "GUI"). Importing this package imports Qt."""
from app.gui.main_window import MainWindow

__all__ = ["MainWindow"]
