"""``python -m scenesig ...`` is the ``scenesig`` console script."""
import sys

from scenesig.cli import main

sys.exit(main())
