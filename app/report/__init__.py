"""The workspace report: ``report.html`` (self-contained, with pictures) and the terminal summary.

- :mod:`reflab.app.report.data`: the workspace's files read defensively (:class:`~reflab.app.report.data.Sources`)
  and the text summary;
- :mod:`reflab.app.report.sections`: one module per section (captures, camera, lights, geometry, fit,
  texture, views, error against run time), each comparing with ``truth/`` when it exists, and
  ``section.py``, the Section type and number formatting they share;
- :mod:`reflab.app.report.figures`: pictures as embedded PNG data URIs (OpenCV, matplotlib);
- :mod:`reflab.app.report.build`: renders the model and views and fills ``templates/report.html.j2`` (Jinja2).
"""
