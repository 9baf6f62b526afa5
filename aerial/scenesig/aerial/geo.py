"""Geo-referenced map tiles: the ``map.csv`` reader and pixel <-> latitude/longitude <-> local metres.

A tile folder holds images and a ``map.csv`` with one row per tile::

    Filename,Top_left_lat,Top_left_lon,Bottom_right_lat,Bottom_right_long
    "sat_map_00.jpg",60.403962,22.460441,60.402409,22.464059

(WGS-84 degrees of the outer corners of the top-left and bottom-right pixels; the WildNav layout).
The tiles are north-up web-map imagery, so longitude is linear in the pixel column and latitude is
linear in the *Mercator* ordinate ``ln tan(pi/4 + lat/2)`` of the pixel row; over a tile of 200 m
the difference from a plain linear latitude is about a millimetre, but the Mercator form is the
correct one and costs nothing.

Local metres are east/north on the local tangent plane at an origin (default: the centre of all
tiles), ``east = R cos(lat0) dlon``, ``north = R dlat`` with the WGS-84 equatorial radius -- exact
to a few centimetres over the few kilometres a tile set covers, so neither pyproj nor utm is needed.

Pixel coordinates follow OpenCV: pixel (column c, row r) has its centre at ``x = c, y = r``, so
the tile's outer corners are at ``(-0.5, -0.5)`` and ``(W - 0.5, H - 0.5)``.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenesig.surveys.errors import DataError
from scenesig.surveys.validation import csv_header

__all__ = ["Tile", "TileSet", "load_tiles", "EARTH_RADIUS_M", "MAP_COLUMNS"]

#: WGS-84 equatorial radius (m).
EARTH_RADIUS_M = 6378137.0

#: Columns of ``map.csv``, in order.
MAP_COLUMNS = ("Filename", "Top_left_lat", "Top_left_lon", "Bottom_right_lat", "Bottom_right_long")


def _mercator(lat_deg):
    return np.log(np.tan(np.pi / 4 + np.radians(lat_deg) / 2))


def _inverse_mercator(y):
    return np.degrees(2 * np.arctan(np.exp(y)) - np.pi / 2)


@dataclass
class Tile:
    """One geo-referenced tile.

    Attributes
    ----------
    name : str
        File name (as in ``map.csv``).
    path : Path
    top_left : (lat, lon)
        Outer corner of the top-left pixel, degrees.
    bottom_right : (lat, lon)
        Outer corner of the bottom-right pixel, degrees.
    size : (width, height)
        Pixels (read from the image on first use when not given).
    """

    name: str
    path: Path
    top_left: tuple[float, float]
    bottom_right: tuple[float, float]
    size: tuple[int, int] | None = None
    _image: np.ndarray | None = field(default=None, repr=False, compare=False)

    # ------------------------------------------------------------------ image
    def image(self) -> np.ndarray:
        """The tile as a BGR uint8 array (read once, then cached)."""
        if self._image is None:
            import cv2

            img = cv2.imread(str(self.path), cv2.IMREAD_COLOR)
            if img is None:
                raise DataError(self.path, "cannot read or decode the tile image")
            if self.size is not None and (img.shape[1], img.shape[0]) != tuple(self.size):
                raise DataError(self.path, f"tile is {img.shape[1]}x{img.shape[0]} px, expected "
                                           f"{self.size[0]}x{self.size[1]}")
            self._image = img
            self.size = (img.shape[1], img.shape[0])
        return self._image

    def _wh(self) -> tuple[int, int]:
        if self.size is None:
            self.image()
        return self.size

    # ------------------------------------------------------------------ geometry
    def pixel_to_latlon(self, xy) -> np.ndarray:
        """Pixel coordinates ``(..., 2)`` (x right, y down) -> ``(..., 2)`` (lat, lon) degrees."""
        xy = np.asarray(xy, dtype=float)
        w, h = self._wh()
        u = (xy[..., 0] + 0.5) / w
        v = (xy[..., 1] + 0.5) / h
        lon = self.top_left[1] + u * (self.bottom_right[1] - self.top_left[1])
        m0, m1 = _mercator(self.top_left[0]), _mercator(self.bottom_right[0])
        lat = _inverse_mercator(m0 + v * (m1 - m0))
        return np.stack([lat, lon], axis=-1)

    def latlon_to_pixel(self, latlon) -> np.ndarray:
        """``(..., 2)`` (lat, lon) degrees -> pixel coordinates ``(..., 2)``."""
        ll = np.asarray(latlon, dtype=float)
        w, h = self._wh()
        u = (ll[..., 1] - self.top_left[1]) / (self.bottom_right[1] - self.top_left[1])
        m0, m1 = _mercator(self.top_left[0]), _mercator(self.bottom_right[0])
        v = (_mercator(ll[..., 0]) - m0) / (m1 - m0)
        return np.stack([u * w - 0.5, v * h - 0.5], axis=-1)

    def contains(self, latlon) -> np.ndarray:
        """Whether (lat, lon) lies on the tile."""
        ll = np.asarray(latlon, dtype=float)
        return ((ll[..., 0] <= self.top_left[0]) & (ll[..., 0] >= self.bottom_right[0])
                & (ll[..., 1] >= self.top_left[1]) & (ll[..., 1] <= self.bottom_right[1]))

    @property
    def centre_latlon(self) -> tuple[float, float]:
        return ((self.top_left[0] + self.bottom_right[0]) / 2,
                (self.top_left[1] + self.bottom_right[1]) / 2)

    def metres_per_pixel(self) -> tuple[float, float]:
        """Ground sampling distance (east, north) in metres per pixel at the tile centre."""
        w, h = self._wh()
        lat0 = math.radians(self.centre_latlon[0])
        dx = EARTH_RADIUS_M * math.cos(lat0) * math.radians(self.bottom_right[1] - self.top_left[1])
        dy = EARTH_RADIUS_M * math.radians(self.top_left[0] - self.bottom_right[0])
        return dx / w, dy / h


@dataclass
class TileSet:
    """The tiles of one folder, with a local east/north frame.

    Attributes
    ----------
    root : Path
    tiles : list of Tile
    origin : (lat, lon)
        Origin of the local metric frame (default: centre of the tiles' extent).
    """

    root: Path
    tiles: list
    origin: tuple[float, float] = (0.0, 0.0)

    def __len__(self) -> int:
        return len(self.tiles)

    def __iter__(self):
        return iter(self.tiles)

    def __getitem__(self, key) -> Tile:
        if isinstance(key, str):
            for t in self.tiles:
                if t.name == key or Path(t.name).stem == key:
                    return t
            raise KeyError(f"no tile {key!r} in {self.root}")
        return self.tiles[key]

    def index(self, name: str) -> int:
        return [t.name for t in self.tiles].index(self[name].name)

    def latlon_to_local(self, latlon) -> np.ndarray:
        """``(..., 2)`` (lat, lon) -> ``(..., 2)`` (east, north) metres from :attr:`origin`."""
        ll = np.asarray(latlon, dtype=float)
        lat0, lon0 = self.origin
        east = EARTH_RADIUS_M * math.cos(math.radians(lat0)) * np.radians(ll[..., 1] - lon0)
        north = EARTH_RADIUS_M * np.radians(ll[..., 0] - lat0)
        return np.stack([east, north], axis=-1)

    def local_to_latlon(self, en) -> np.ndarray:
        """``(..., 2)`` (east, north) metres -> ``(..., 2)`` (lat, lon)."""
        en = np.asarray(en, dtype=float)
        lat0, lon0 = self.origin
        lat = lat0 + np.degrees(en[..., 1] / EARTH_RADIUS_M)
        lon = lon0 + np.degrees(en[..., 0] / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return np.stack([lat, lon], axis=-1)

    def tile_at(self, latlon) -> Tile | None:
        """The tile holding (lat, lon) (the one whose centre is nearest when tiles overlap)."""
        ll = np.asarray(latlon, dtype=float)
        best, best_d = None, np.inf
        for t in self.tiles:
            if bool(t.contains(ll)):
                d = float(np.hypot(*(ll - np.asarray(t.centre_latlon))))
                if d < best_d:
                    best, best_d = t, d
        return best


def _float(value: str, path: Path, line: int, column: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise DataError(path, f"{column} is not a number: {value!r}", line) from None
    if not math.isfinite(v):
        raise DataError(path, f"{column} is not finite: {value!r}", line)
    return v


def load_tiles(root, check_images: bool = True) -> TileSet:
    """Read ``ROOT/map.csv`` and the tiles it lists.

    Parameters
    ----------
    root : path
        Folder with ``map.csv`` and the tile images.
    check_images : bool
        Check that every listed image exists (they are decoded lazily, on first use).

    Returns
    -------
    TileSet

    Raises
    ------
    surveys.errors.DataError
        Missing folder or ``map.csv``, missing columns, a bad number, corners in the wrong order
        (top-left must be north-west of bottom-right), duplicate or missing tile files.
    """
    root = Path(root)
    path = root / "map.csv"
    if not root.is_dir():
        raise DataError(root, "tile folder not found")
    if not path.is_file():
        raise DataError(path, "map.csv not found (one row per tile: " + ",".join(MAP_COLUMNS) + ")")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(path, f"cannot read: {e}") from None
    reader = csv.reader(text.splitlines())
    header = csv_header(reader, path, MAP_COLUMNS)
    col = {c: header.index(c) for c in MAP_COLUMNS}
    tiles, seen = [], set()
    for line, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) < len(header):
            raise DataError(path, f"expected {len(header)} fields, got {len(row)}", line)
        name = row[col["Filename"]].strip()
        if not name:
            raise DataError(path, "empty Filename", line)
        if name in seen:
            raise DataError(path, f"tile {name} listed twice", line)
        seen.add(name)
        tl = (_float(row[col["Top_left_lat"]], path, line, "Top_left_lat"),
              _float(row[col["Top_left_lon"]], path, line, "Top_left_lon"))
        br = (_float(row[col["Bottom_right_lat"]], path, line, "Bottom_right_lat"),
              _float(row[col["Bottom_right_long"]], path, line, "Bottom_right_long"))
        for lat in (tl[0], br[0]):
            if not -85.0 < lat < 85.0:
                raise DataError(path, f"latitude {lat} outside (-85, 85)", line)
        if not (tl[0] > br[0] and br[1] > tl[1]):
            raise DataError(path, f"top-left {tl} must lie north-west of bottom-right {br}", line)
        tpath = root / name
        if check_images and not tpath.is_file():
            raise DataError(tpath, f"tile image listed in {path.name} (line {line}) not found")
        tiles.append(Tile(name, tpath, tl, br))
    if not tiles:
        raise DataError(path, "no tiles listed")
    lats = [v for t in tiles for v in (t.top_left[0], t.bottom_right[0])]
    lons = [v for t in tiles for v in (t.top_left[1], t.bottom_right[1])]
    origin = ((min(lats) + max(lats)) / 2, (min(lons) + max(lons)) / 2)
    return TileSet(root, tiles, origin)
