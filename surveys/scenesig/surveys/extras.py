"""Optional dependencies (``pip install "scenesig[EXTRA]"``) and the one error a feature raises without one.

The default path -- simulate, build a map on this machine, localise, report -- needs neither Dask nor
pycolmap.  Building or comparing on a Dask cluster (``--scheduler``) needs the ``distributed`` extra;
pycolmap's absolute-pose estimator (``pnp.estimator = "pycolmap"``) needs the ``colmap`` extra.
"""
from __future__ import annotations

import importlib

__all__ = ["EXTRAS", "MissingExtraError", "require"]

#: extra name -> the modules it provides (pyproject.toml's ``[project.optional-dependencies]``)
EXTRAS = {"distributed": ("dask", "distributed"), "colmap": ("pycolmap",)}


class MissingExtraError(ImportError):
    """A feature needs an optional dependency that is not installed; the message says which extra gives it.

    Attributes
    ----------
    extra : the extra to install (``pip install "scenesig[extra]"``).
    feature : what needed it.
    """

    def __init__(self, module: str, extra: str, feature: str):
        self.extra, self.feature = extra, feature
        super().__init__(f"{feature} needs the optional dependency {module!r}, which is not installed: "
                         f"pip install \"scenesig[{extra}]\"", name=module)


def require(module: str, extra: str, feature: str):
    """Import ``module`` and return it, or raise :class:`MissingExtraError` naming ``extra`` and ``feature``."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if getattr(exc, "name", None) not in (None, module, module.split(".")[0]):
            raise               # the module is there but one of its own imports failed: not ours to rename
        raise MissingExtraError(module, extra, feature) from None
