"""The report's sections, one module each (captures, camera, lights, geometry, fit, texture, views,
error against run time), and :mod:`~reflab.app.report.sections.section`, what they share.

Each ``*_section(src, ...)`` returns a :class:`~reflab.app.report.sections.section.Section` (None when its
stage left nothing). Fields are read defensively: a value that is present is shown, a missing one
is skipped, so files from older or newer versions of a stage still report. Where ``truth/`` exists
(docs/formats.md, "The simulated lab's truth") each section adds the error against it.
"""
