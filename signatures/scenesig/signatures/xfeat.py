"""XFeat learned local features (Potje et al., "XFeat: Accelerated Features for Lightweight Image
Matching", CVPR 2024): the ONNX backbone and the project's own numpy post-processing.

The network (``xfeat.onnx``, Apache-2.0, from github.com/verlab/accelerated_features) runs with
``onnxruntime`` alone on a fixed 640 x 640 input and returns three maps at 1/8 resolution: dense
64-channel descriptors, 65-channel keypoint logits and a reliability map.  What upstream's
``detectAndCompute`` does with them is redone here in numpy (:func:`postprocess`):

1. softmax over the 65 logit channels, drop the last ("no keypoint in this 8 x 8 cell") and
   pixel-shuffle the other 64 into the cell: a full-resolution keypoint heat map;
2. keypoints are its local maxima over 5 x 5 pixels above 0.05 (non-maximum suppression);
3. score = heat map at the keypoint (nearest) x reliability (bilinear); the ``top_k`` best (4096);
4. descriptors: the dense map L2-normalised per cell, sampled at the keypoints bicubically (as
   PyTorch's ``grid_sample`` with ``align_corners=False`` and zero padding, which upstream uses),
   L2-normalised again;
5. keypoints scaled back to the input image.

Images of any size: ``fit="tile"`` (default) runs the network on 640 x 640 tiles of the image at its
own resolution (zero-padded where the image is smaller) and stitches the 1/8-resolution maps, each
cell from the tile whose centre is nearest -- what upstream computes on the whole image, up to the
tiles' borders; a 1024 x 384 GRIEF image is two tiles, a VGA frame one.  ``fit="fit"`` scales the
image down to fit one tile (faster; coarser keypoints).

Matching (:func:`match_mnn`) is upstream's ``match``: mutual nearest neighbours on cosine similarity,
kept when the similarity exceeds ``min_cossim`` (0.82, the default of upstream's ``XFeat.match``).

The model file is found by :func:`model_path`: a ``model`` setting, else the model a caller named
with :func:`using_model` (a context variable: this thread or task only), else the environment variable
``SCENESIG_XFEAT_MODEL``, else :data:`DEFAULT_MODEL_PATH` (``~/.local/share/scenesig/models/xfeat.onnx``,
under ``$XDG_DATA_HOME`` when set).  ``onnxruntime`` is the optional extra ``scenesig[learned]``.
"""
from __future__ import annotations

import contextlib
import contextvars
import hashlib
import os
import threading
from pathlib import Path

import numpy as np
from scipy import ndimage

from scenesig.surveys.errors import DataError
from scenesig.surveys.settings import merge_settings

__all__ = ["default_config", "ENV_VAR", "DEFAULT_MODEL_PATH", "INPUT_SIZE", "ModelNotFoundError", "model_path", "using_model",
           "model_sha256", "XFeat", "DenseMaps", "heatmap_from_logits", "nms", "sample_dense", "postprocess",
           "match_mnn", "get_xfeat"]

#: The network's fixed input side (pixels) and output stride.
INPUT_SIZE = 640
STRIDE = 8
#: Environment variable naming the model file.
ENV_VAR = "SCENESIG_XFEAT_MODEL"


def _default_model_path() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "scenesig" / "models" / "xfeat.onnx"


#: Where the model is looked for when neither the setting nor the environment variable names it.
DEFAULT_MODEL_PATH = _default_model_path()

# The model :func:`using_model` names: a context variable, not the process environment -- the library
# keeps no process state, and one thread naming a model does not change another's lookup.
_USING_MODEL: contextvars.ContextVar = contextvars.ContextVar("scenesig_xfeat_model", default=None)

default_config = {
    "model": None,               # path of xfeat.onnx; None: $SCENESIG_XFEAT_MODEL, else DEFAULT_MODEL_PATH
    "top_k": 4096,               # upstream's default
    "detection_threshold": 0.05,  # upstream's NMS threshold on the heat map
    "nms_kernel": 5,             # upstream's 5 x 5 non-maximum suppression
    "descriptor_interpolation": "bicubic",   # upstream's InterpolateSparse2d('bicubic')
    "fit": "tile",               # "tile": native resolution, 640 x 640 tiles; "fit": scaled into one tile
    "min_cossim": 0.82,          # upstream XFeat.match's default
    "threads": 1,                # onnxruntime intra-op threads
}


class ModelNotFoundError(DataError):
    """The XFeat model file is not where the settings say (the message lists where it looked)."""


def _merge(config: dict | None) -> dict:
    cfg = merge_settings(default_config, config, "xfeat")
    if cfg["fit"] not in ("tile", "fit"):
        raise ValueError(f"xfeat fit must be 'tile' or 'fit', got {cfg['fit']!r}")
    if cfg["descriptor_interpolation"] not in ("bicubic", "bilinear"):
        raise ValueError(f"xfeat descriptor_interpolation must be 'bicubic' or 'bilinear', "
                         f"got {cfg['descriptor_interpolation']!r}")
    return cfg


def model_path(setting=None) -> Path:
    """The model file: ``setting``, else the one named by an enclosing :func:`using_model`, else
    ``$SCENESIG_XFEAT_MODEL``, else :data:`DEFAULT_MODEL_PATH`.

    Raises
    ------
    ModelNotFoundError
        The chosen file does not exist; the message says which source named it and how to get it.
    """
    if setting:
        path, source = Path(setting).expanduser(), "the 'model' setting"
    elif _USING_MODEL.get():
        path, source = Path(_USING_MODEL.get()).expanduser(), "scenesig.signatures.xfeat.using_model"
    elif os.environ.get(ENV_VAR):
        path, source = Path(os.environ[ENV_VAR]).expanduser(), f"${ENV_VAR}"
    else:
        path, source = _default_model_path(), f"the default location (neither the 'model' setting nor ${ENV_VAR} is set)"
    if not path.is_file():
        raise ModelNotFoundError(path, f"XFeat model not found (looked at {path}, from {source}). Get "
                                       f"weights/xfeat.onnx from github.com/verlab/accelerated_features "
                                       f"(Apache-2.0) and put it there, or set ${ENV_VAR} to its path")
    return path


@contextlib.contextmanager
def using_model(path=None):
    """Within: :func:`model_path` finds ``path`` when no ``model`` setting names one (None: nothing
    changes).  For callers that must name the model for code that takes no setting -- learned cells
    (:func:`scenesig.signatures.hog.describe_cells`) look the model up the library's way, since a bank
    must not store a machine's path.

    The name is held in a context variable, never in ``os.environ``: it holds for this thread (or
    asyncio task) until the block ends, nests, and is not seen by other threads or by processes
    started inside the block -- code that runs elsewhere enters its own ``using_model``.
    """
    if not path:
        yield
        return
    token = _USING_MODEL.set(str(path))
    try:
        yield
    finally:
        _USING_MODEL.reset(token)


_SHA: dict = {}


def model_sha256(path) -> str:
    """sha256 of the model file (hex), computed once per path and size."""
    path = Path(path)
    key = (str(path.resolve()), path.stat().st_size, path.stat().st_mtime_ns)
    if key not in _SHA:
        _SHA[key] = hashlib.sha256(path.read_bytes()).hexdigest()
    return _SHA[key]


# --------------------------------------------------------------------------------- post-processing
def heatmap_from_logits(logits: np.ndarray) -> np.ndarray:
    """(65, h, w) keypoint logits -> (8h, 8w) heat map: softmax over channels, the "no keypoint"
    channel dropped, channel ``c`` placed at row ``c // 8``, column ``c % 8`` of its cell."""
    z = logits - logits.max(axis=0, keepdims=True)
    e = np.exp(z)
    p = e[:64] / e.sum(axis=0, keepdims=True)
    _, h, w = p.shape
    return p.reshape(STRIDE, STRIDE, h, w).transpose(2, 0, 3, 1).reshape(h * STRIDE, w * STRIDE)


def nms(heat: np.ndarray, threshold: float = 0.05, kernel: int = 5) -> np.ndarray:
    """(N, 2) integer (x, y) of the pixels equal to their ``kernel`` x ``kernel`` maximum and above
    ``threshold``, in row-major order (as upstream's ``nonzero``)."""
    local = ndimage.maximum_filter(heat, size=kernel, mode="constant", cval=-np.inf)
    ys, xs = np.nonzero((heat == local) & (heat > threshold))
    return np.column_stack([xs, ys])


def _cubic_weights(t: np.ndarray, a: float = -0.75) -> np.ndarray:
    """(N, 4) cubic-convolution weights of taps -1, 0, 1, 2 for fractions ``t`` (PyTorch's A = -0.75)."""
    def near(x):
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x):
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], axis=1)


def sample_dense(dense: np.ndarray, xy: np.ndarray, size, mode: str = "bilinear") -> np.ndarray:
    """Sample a (C, h, w) map at (N, 2) pixel positions of an image of ``size`` (width, height).

    As upstream's ``InterpolateSparse2d``: positions normalised by ``size - 1`` to [-1, 1] and sampled
    with ``grid_sample(align_corners=False)``, zero outside the map.  Returns (N, C).
    """
    c, h, w = dense.shape
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    W, H = float(size[0]), float(size[1])
    u = xy[:, 0] * w / max(W - 1, 1.0) - 0.5
    v = xy[:, 1] * h / max(H - 1, 1.0) - 0.5
    if mode == "nearest":
        ui, vi = np.rint(u).astype(int), np.rint(v).astype(int)
        ok = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
        out = np.zeros((len(xy), c), dense.dtype)
        out[ok] = dense[:, vi[ok], ui[ok]].T
        return out
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    tu, tv = u - u0, v - v0
    if mode == "bilinear":
        wu = np.stack([1 - tu, tu], axis=1)
        wv = np.stack([1 - tv, tv], axis=1)
        offs = (0, 1)
    elif mode == "bicubic":
        wu, wv = _cubic_weights(tu), _cubic_weights(tv)
        offs = (-1, 0, 1, 2)
    else:
        raise ValueError(f"unknown interpolation {mode!r}")
    out = np.zeros((len(xy), c))
    for j, dv in enumerate(offs):
        vv = v0 + dv
        okv = (vv >= 0) & (vv < h)
        for i, du in enumerate(offs):
            uu = u0 + du
            ok = okv & (uu >= 0) & (uu < w)
            wt = wu[:, i] * wv[:, j] * ok
            out += wt[:, None] * dense[:, np.clip(vv, 0, h - 1), np.clip(uu, 0, w - 1)].T
    return out


def _l2(x: np.ndarray, axis: int) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=axis, keepdims=True), 1e-12)


class DenseMaps:
    """The network's outputs over one image (stitched from tiles), cropped to the image's canvas.

    Attributes
    ----------
    descriptors : (64, h, w) dense descriptors; logits : (65, h, w); reliability : (1, h, w).
    canvas : (width, height) in network pixels (8 w, 8 h).
    scale : (sx, sy) image pixels per network pixel.
    valid : (width, height) of the part of the canvas the image covers (network pixels).
    """

    def __init__(self, descriptors, logits, reliability, canvas, scale=(1.0, 1.0), valid=None):
        self.descriptors = descriptors
        self.logits = logits
        self.reliability = reliability
        self.canvas = tuple(int(v) for v in canvas)
        self.scale = tuple(float(s) for s in scale)
        self.valid = self.canvas if valid is None else tuple(float(v) for v in valid)


def postprocess(maps: DenseMaps, top_k: int = 4096, threshold: float = 0.05, kernel: int = 5,
                interpolation: str = "bicubic"):
    """Keypoints, scores and descriptors from the network's maps (upstream's ``detectAndCompute``).

    Returns
    -------
    xy : (N, 2) float32 keypoints in image pixels, best first; scores : (N,) float32 (> 0);
    descriptors : (N, 64) float32, unit length.
    """
    heat = heatmap_from_logits(maps.logits.astype(np.float64))
    kp = nms(heat, threshold, kernel)
    # keypoints in the zero padding beyond the image are not the image's
    kp = kp[(kp[:, 0] < maps.valid[0]) & (kp[:, 1] < maps.valid[1])]
    size = maps.canvas
    score = sample_dense(heat[None], kp, size, "nearest")[:, 0] * \
        sample_dense(maps.reliability.astype(np.float64), kp, size, "bilinear")[:, 0]
    order = np.argsort(-score, kind="stable")[: max(int(top_k), 0)]
    order = order[score[order] > 0]
    kp, score = kp[order], score[order]
    dense = _l2(maps.descriptors.astype(np.float64), axis=0)
    desc = _l2(sample_dense(dense, kp, size, interpolation), axis=1)
    xy = kp * np.asarray(maps.scale)
    return xy.astype(np.float32), score.astype(np.float32), desc.astype(np.float32)


def match_mnn(da: np.ndarray, db: np.ndarray, min_cossim: float = 0.82):
    """Mutual nearest neighbours of unit descriptors on cosine similarity (upstream's ``XFeat.match``).

    Returns ``(ia, ib, cossim)``: index pairs into ``da`` and ``db`` and their similarity; a pair is
    kept when each is the other's most similar and the similarity exceeds ``min_cossim`` (<= -1: no
    threshold, as upstream's ``match_xfeat``).
    """
    if not len(da) or not len(db):
        z = np.zeros(0, np.int64)
        return z, z.copy(), np.zeros(0, np.float32)
    sim = np.asarray(da, np.float32) @ np.asarray(db, np.float32).T
    ab = sim.argmax(axis=1)
    ba = sim.argmax(axis=0)
    ia = np.flatnonzero(ba[ab] == np.arange(len(da)))
    ib = ab[ia]
    s = sim[ia, ib]
    if min_cossim > -1:
        keep = s > min_cossim
        ia, ib, s = ia[keep], ib[keep], s[keep]
    return ia, ib, s


# ------------------------------------------------------------------------------------------ network
def _tile_offsets(size: int) -> list[int]:
    """Tile origins (multiples of the stride) covering ``size`` pixels with 640-pixel tiles."""
    if size <= INPUT_SIZE:
        return [0]
    n = int(np.ceil((size - INPUT_SIZE) / (INPUT_SIZE - 64))) + 1       # at least 64 px of overlap
    last = size - INPUT_SIZE
    return sorted({int(np.floor(o / STRIDE)) * STRIDE for o in np.linspace(0, last, n)} | {int(np.ceil(last / STRIDE)) * STRIDE})


def _owner(n_cells: int, offsets: list[int]) -> np.ndarray:
    """For each 1/8 cell along one axis, the tile whose centre is nearest its centre."""
    centres = np.arange(n_cells) * STRIDE + STRIDE / 2
    tiles = np.asarray(offsets, float) + INPUT_SIZE / 2
    return np.argmin(np.abs(centres[:, None] - tiles[None]), axis=1)


class XFeat:
    """The XFeat network (onnxruntime) and the post-processing, with the settings of :data:`default_config`."""

    def __init__(self, config: dict | None = None):
        self.config = _merge(config)
        self.path = model_path(self.config["model"])
        try:
            import onnxruntime as ort
        except ImportError:
            raise DataError(self.path, "XFeat needs onnxruntime: pip install 'scenesig[learned]' "
                                       "(or pip install onnxruntime)") from None
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(self.config["threads"])
        opts.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for a bad file
            raise DataError(self.path, f"not a usable XFeat ONNX model: {exc}") from None
        names = [o.name for o in self.session.get_outputs()]
        shapes = {o.name: o.shape for o in self.session.get_outputs()}
        try:
            self._out = {next(n for n in names if shapes[n][1] == c): key
                         for c, key in ((64, "descriptors"), (65, "logits"), (1, "reliability"))}
        except StopIteration:
            raise DataError(self.path, f"unexpected XFeat outputs {shapes}: expected 64-, 65- and 1-channel "
                                       f"maps at 1/8 resolution") from None
        self.input_name = self.session.get_inputs()[0].name
        self.sha256 = model_sha256(self.path)

    def describe(self) -> dict:
        """The model file and settings, for a method's configuration record."""
        return {"model": str(self.path), "model_sha256": self.sha256,
                **{k: v for k, v in self.config.items() if k != "model"}}

    def _run(self, tile: np.ndarray) -> dict:
        """One 640 x 640 float32 gray tile in [0, 1] -> the three maps."""
        x = np.ascontiguousarray(np.broadcast_to(tile[None, None], (1, 3, INPUT_SIZE, INPUT_SIZE)), np.float32)
        outs = self.session.run(list(self._out), {self.input_name: x})
        return {self._out[n]: o[0] for n, o in zip(self._out, outs)}

    def dense(self, image: np.ndarray) -> DenseMaps:
        """The network's maps over a uint8 gray or colour image (see the module docstring's ``fit``).

        The network averages the three channels first, so a gray image is given as itself.
        """
        img = np.asarray(image)
        if img.ndim == 3:
            img = img.mean(axis=2)
        if img.ndim != 2 or not img.size:
            raise ValueError(f"expected a 2-D gray or 3-channel image, got shape {np.shape(image)}")
        g = img.astype(np.float32) / 255.0
        H, W = g.shape
        scale = (1.0, 1.0)
        if self.config["fit"] == "fit" and max(H, W) > INPUT_SIZE:
            import cv2

            f = INPUT_SIZE / max(H, W)
            w2, h2 = max(1, int(round(W * f))), max(1, int(round(H * f)))
            g = cv2.resize(g, (w2, h2), interpolation=cv2.INTER_AREA)
            scale = (W / w2, H / h2)
            H, W = h2, w2
        hc, wc = -(-H // STRIDE), -(-W // STRIDE)         # cells covering the image
        canvas = np.zeros((hc * STRIDE, wc * STRIDE), np.float32)
        canvas[:H, :W] = g
        oy, ox = _tile_offsets(canvas.shape[0]), _tile_offsets(canvas.shape[1])
        own_y, own_x = _owner(hc, oy), _owner(wc, ox)
        out = {"descriptors": np.zeros((64, hc, wc), np.float32), "logits": np.zeros((65, hc, wc), np.float32),
               "reliability": np.zeros((1, hc, wc), np.float32)}
        for ty, y0 in enumerate(oy):
            for tx, x0 in enumerate(ox):
                rows, cols = np.flatnonzero(own_y == ty), np.flatnonzero(own_x == tx)
                if not len(rows) or not len(cols):
                    continue
                tile = np.zeros((INPUT_SIZE, INPUT_SIZE), np.float32)
                part = canvas[y0:y0 + INPUT_SIZE, x0:x0 + INPUT_SIZE]
                tile[:part.shape[0], :part.shape[1]] = part
                maps = self._run(tile)
                r0, c0 = y0 // STRIDE, x0 // STRIDE
                for key, m in maps.items():
                    out[key][:, rows[:, None], cols[None]] = m[:, rows[:, None] - r0, cols[None] - c0]
        return DenseMaps(out["descriptors"], out["logits"], out["reliability"], (wc * STRIDE, hc * STRIDE),
                         scale, (W, H))

    def cells(self, image: np.ndarray, cell: int = STRIDE) -> np.ndarray:
        """The dense descriptor map as cell features: ``(H // 8, W // 8, 64)`` float32, unit length
        per cell (as upstream normalises its sampled descriptors), cell ``(r, c)`` covering pixels
        ``[8r, 8r + 8) x [8c, 8c + 8)`` like an FHOG cell (:func:`scenesig.signatures.hog.describe_cells`).

        An image smaller than the network's 640 x 640 input is extended by mirroring, not by zeros:
        the network normalises its input over the whole tile (instance normalisation), so zero
        padding would change every cell's descriptor with the size of the image -- with each level
        of a pyramid differently.
        """
        if int(cell) != STRIDE:
            raise ValueError(f"XFeat cells are {STRIDE} pixels (its map is at 1/{STRIDE} resolution), got {cell}")
        if self.config["fit"] != "tile":
            raise ValueError("XFeat cells need fit='tile' (the map at the image's own resolution)")
        g = np.asarray(image, np.float32)
        if g.ndim == 3:
            g = g.mean(axis=2)
        if g.ndim != 2:
            raise ValueError(f"expected a 2-D gray or 3-channel image, got shape {np.shape(image)}")
        H, W = g.shape
        hc, wc = H // STRIDE, W // STRIDE
        if hc < 1 or wc < 1:
            raise ValueError(f"image {g.shape} is smaller than one {STRIDE}-px cell")
        ph, pw = max(0, INPUT_SIZE - H), max(0, INPUT_SIZE - W)
        if ph or pw:
            g = np.pad(g, ((0, ph), (0, pw)), mode="symmetric")
        d = self.dense(g).descriptors[:, :hc, :wc]
        out = np.ascontiguousarray(np.moveaxis(d, 0, 2), np.float32)
        out /= np.maximum(np.linalg.norm(out, axis=2, keepdims=True), np.float32(1e-12))
        return out

    def detect_and_compute(self, image: np.ndarray, top_k: int | None = None):
        """``(xy, scores, descriptors)`` of an image (:func:`postprocess` of :meth:`dense`)."""
        cfg = self.config
        return postprocess(self.dense(image), cfg["top_k"] if top_k is None else int(top_k),
                           cfg["detection_threshold"], int(cfg["nms_kernel"]), cfg["descriptor_interpolation"])


_MODELS: dict = {}
_MODELS_LOCK = threading.Lock()


def get_xfeat(config: dict | None = None) -> XFeat:
    """A shared :class:`XFeat` per model file and settings (the session is loaded once per process)."""
    cfg = _merge(config)
    key = (str(model_path(cfg["model"])), repr(sorted(cfg.items())))
    with _MODELS_LOCK:
        if key not in _MODELS:
            _MODELS[key] = XFeat(cfg)
        return _MODELS[key]
