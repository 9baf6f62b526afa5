"""The one settings mechanism: a component's ``default_config`` dict, overridden by a caller's dict.

Every configurable function or class of the project takes ``config: dict | None`` -- overrides of its
module's ``default_config`` -- and merges them with :func:`merge_settings`, so every component treats a
misspelt option the same way: a ``ValueError`` naming the unknown keys and the known ones, instead of an
option silently ignored.  Nested dicts are merged key by key (``{"match": {"ratio": 0.8}}`` changes one
entry of ``match``) and checked the same way, except the ``open`` ones: sub-dicts a component passes on
whole to another component, which checks them with its own ``default_config``.
"""
from __future__ import annotations

from collections.abc import Mapping

__all__ = ["merge_settings"]


def _copy(value):
    return {k: _copy(v) for k, v in value.items()} if isinstance(value, Mapping) else value


def merge_settings(defaults: Mapping, overrides: Mapping | None = None, what: str = "", open: tuple = ()) -> dict:
    """``defaults`` with ``overrides`` applied, as a new dict (the defaults are never modified).

    Parameters
    ----------
    defaults : the component's ``default_config``.
    overrides : the caller's changes, or None.
    what : the component's name for messages, e.g. ``"build"`` -> "unknown build option(s) ...".
    open : keys of nested dicts that are merged but not checked here (another component checks them).

    Raises
    ------
    ValueError
        On keys of ``overrides`` (at any level below a checked dict) that ``defaults`` does not have,
        naming them and the known keys.
    TypeError
        When ``overrides`` is not a mapping.
    """
    out = _copy(defaults)
    if overrides is None:
        return out
    if not isinstance(overrides, Mapping):
        raise TypeError(f"{what + ' ' if what else ''}settings must be a dict, got {type(overrides).__name__}")
    unknown = [k for k in overrides if k not in defaults]
    if unknown:
        raise ValueError(f"unknown {what + ' ' if what else ''}option(s) {sorted(map(str, unknown))}; "
                         f"known: {sorted(map(str, defaults))}")
    for k, v in overrides.items():
        d = defaults[k]
        if isinstance(d, Mapping) and isinstance(v, Mapping):
            if k in open:
                out[k] = {**_copy(d), **_copy(v)}
            else:
                out[k] = merge_settings(d, v, f"{what}.{k}" if what else str(k))
        else:
            out[k] = _copy(v)
    return out
