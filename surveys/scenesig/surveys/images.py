"""Strict image decoding: a truncated or corrupt camera frame is an error, never a partly grey frame.

OpenCV's decoders recover from damage silently: libjpeg only prints "Premature end of JPEG file"
on stderr and OpenCV returns the frame with its missing part filled grey, which the localiser would
use and the map builder would mine signatures from.  Here

* **JPEG** is decoded by libjpeg-turbo through ``simplejpeg`` with ``strict=True``: every decoder
  warning (premature end of the file or of a data segment, extraneous bytes before a marker,
  corrupt entropy data) raises.  The pixels are the same as OpenCV's (both are libjpeg-turbo with
  the accurate integer DCT), and it is faster than ``cv2.imdecode`` (no extra colour copy), so strict
  decoding costs nothing (``scenesig bench strict_decode``).  JPEG has no checksum: a bit flip in
  the entropy-coded data that still decodes to valid codes cannot be told from a real frame by any
  decoder; the benchmark measures what share of random bit flips is caught.
* **PNG**: every chunk's CRC-32 is checked and the file must end with ``IEND`` (a truncated file
  has none), then OpenCV decodes it.
* other formats (PPM, BMP, TIFF: the GRIEF originals) must decode with OpenCV.

Every failure raises :class:`scenesig.surveys.errors.CorruptImageError` naming the file.
"""
from __future__ import annotations

import binascii
import struct
from pathlib import Path

import numpy as np

from .errors import CorruptImageError

__all__ = ["read_image", "decode_image", "image_kind", "png_problem"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def image_kind(data: bytes) -> str:
    """``"jpeg"``, ``"png"`` or ``"other"`` from the first bytes."""
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == _PNG_SIGNATURE:
        return "png"
    return "other"


def png_problem(data: bytes) -> str | None:
    """What is wrong with a PNG's chunk structure (None: every CRC matches and it ends with IEND)."""
    mv = memoryview(data)
    pos, n, first = 8, len(data), True
    seen_idat = False
    while pos < n:
        if pos + 12 > n:
            return f"truncated PNG: chunk header at byte {pos} is cut off"
        length, ctype = struct.unpack(">I4s", mv[pos:pos + 8])
        end = pos + 12 + length
        if end > n:
            return f"truncated PNG: chunk {ctype!r} at byte {pos} needs {length} bytes, the file ends first"
        (crc,) = struct.unpack(">I", mv[end - 4:end])
        if binascii.crc32(mv[pos + 4:end - 4]) != crc:
            return f"corrupt PNG: CRC mismatch in chunk {ctype!r} at byte {pos}"
        if first and ctype != b"IHDR":
            return "corrupt PNG: first chunk is not IHDR"
        first = False
        seen_idat |= ctype == b"IDAT"
        if ctype == b"IEND":
            return None if seen_idat else "corrupt PNG: no image data (IDAT) before IEND"
        pos = end
    return "truncated PNG: no IEND chunk (the file ends early)"


def decode_image(data: bytes, path, gray: bool = False) -> np.ndarray:
    """Decode image bytes strictly: BGR (or gray) uint8; :class:`CorruptImageError` naming ``path``."""
    kind = image_kind(data)
    if kind == "jpeg":
        import simplejpeg

        try:
            img = simplejpeg.decode_jpeg(data, colorspace="GRAY" if gray else "BGR", strict=True)
        except ValueError as exc:
            raise CorruptImageError(path, f"corrupt or truncated JPEG ({exc})") from None
        return img[:, :, 0] if gray else img
    if kind == "png":
        problem = png_problem(data)
        if problem:
            raise CorruptImageError(path, problem)
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    if img is None:
        what = "PNG" if kind == "png" else "image (not a JPEG, PNG or other format OpenCV reads)"
        raise CorruptImageError(path, f"{what} does not decode")
    return img


def read_image(path, gray: bool = False) -> np.ndarray:
    """Read and strictly decode an image file (see the module docstring)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CorruptImageError(path, "image file missing") from None
    except OSError as exc:
        raise CorruptImageError(path, f"image file unreadable ({exc.strerror})") from None
    if not data:
        raise CorruptImageError(path, "empty image file")
    return decode_image(data, path, gray)
