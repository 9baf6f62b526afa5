"""scenesig: the application layer -- the ``scenesig`` command line, the demo, the report, the experiments.

The library packages below it (``localiser`` → ``mapping`` → ``signatures`` → ``surveys``) expose plain
functions and never import this package; see ``docs/architecture.md``.
"""
