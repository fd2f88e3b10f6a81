"""The guided lab GUI (`reflab gui`, docs/gui.md): :class:`MainWindow`, loaded on first use.

Importing the package imports nothing; ``reflab.app.gui.MainWindow`` imports Qt and the window.
"""
__all__ = ["MainWindow"]


def __getattr__(name: str):
    if name == "MainWindow":
        from reflab.app.gui.main_window import MainWindow

        return MainWindow
    raise AttributeError(f"module 'reflab.app.gui' has no attribute {name!r}")
