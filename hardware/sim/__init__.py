"""The simulated twin of the lab: the virtual scene (``lab``), its GRBL board on a pseudo-terminal
(``device``), the camera that renders it (``camera``), the props a user puts in front of it
(``props``: circle target, wedge, rod, grey card), the simulated user's marks (``user``) and the
independent reference renderer (``reference``).

The twin may import any stage's types; no product stage imports the twin (tests/test_layers.py).
"""
