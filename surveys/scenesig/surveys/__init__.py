"""Survey runs and what every layer shares: the run format and its readers/writers (``run.py``, ``tum.py``),
the GRIEF adapter (``grief.py``), the simulated survey world (``sim/``), SE(3) and camera geometry
(``geometry.py``), atomic writes (``io.py``), the settings helper (``settings.py``), input validation
(``validation.py``) and the error type for bad input (``errors.py``).

The bottom layer of scenesig (docs/architecture.md): it imports no other scenesig package.
"""
