"""Argument types shared by the command modules."""
from __future__ import annotations

import argparse


def positive_int(s: str) -> int:
    """``argparse`` type: an integer >= 1."""
    v = int(s)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v
