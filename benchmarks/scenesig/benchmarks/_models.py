"""Model files for benchmarks: ``../shared/models`` beside the project, as the data in ``../shared/data``.

A benchmark names the model explicitly so its JSON records which file ran: ``$SCENESIG_XFEAT_MODEL``
when set (a user's choice wins), else ``../shared/models/xfeat/xfeat.onnx`` when present, else the
library's own lookup (:func:`scenesig.signatures.xfeat.model_path`, which says where it looked when nothing is
there).
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["SHARED_MODELS", "xfeat_model"]

SHARED_MODELS = Path(__file__).resolve().parents[4] / "shared" / "models"


def xfeat_model() -> str:
    """Path of the XFeat ONNX model for a benchmark (see the module docstring); raises
    :class:`scenesig.signatures.xfeat.ModelNotFoundError` when there is none."""
    from scenesig.signatures.xfeat import ENV_VAR, model_path

    if os.environ.get(ENV_VAR):
        return str(model_path())
    shared = SHARED_MODELS / "xfeat" / "xfeat.onnx"
    return str(shared if shared.is_file() else model_path())

