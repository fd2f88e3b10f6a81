"""The wizard's pages, one module per step of :data:`reflab.app.gui.stages.STEPS`, on the common
:class:`~reflab.app.gui.pages.page.StepPage` (``page.py``, with the helpers pages share).
:data:`reflab.app.gui.main_window.PAGES` maps each step to its page; this package imports nothing."""
