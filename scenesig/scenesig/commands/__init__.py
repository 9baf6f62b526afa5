"""One module per ``scenesig`` subcommand: ``register(groups)`` declares its arguments, ``run(args)`` does it.

``groups`` maps a group name to an ``argparse`` subparsers object: ``""`` is the top level, the others
(``"bench"``, ``"map"``, ``"experiment"``, ``"import"``, ``"export"``, ``"aerial"``) are second-level
groups created by :mod:`scenesig.cli`.  A command module imports its library code inside ``run()`` so
``scenesig --help`` stays fast.
"""
