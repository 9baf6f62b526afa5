"""Looking at a map: ``scenesig map show maps/NAME [--place P] --out DIR``.

Writes, per place, the keyframe with its signature boxes coloured by landmark depth
(``place_NNNN.png``, like the paper's Fig. 5), a heat map of where signatures sit in the image over all
places (``heatmap.png``, Figs. 5/12), and an overview of places along the route coloured by their
number of signatures (``places.png``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scenesig.mapping.store import MapStore
from scenesig.signatures.bank import Bank
from scenesig.surveys.errors import DataError
from scenesig.surveys.geometry import invert, transform
from scenesig.surveys.io import atomic_path

__all__ = ["place_figure", "heatmap", "show_map", "describe_map"]


def _boxes_and_depths(store: MapStore, data) -> tuple[np.ndarray, np.ndarray]:
    """Signature boxes (x0, y0, x1, y1, pixel edges) in full-resolution pixels and landmark depths (camera z).

    A box is the classifier's candidate shape centred on its firing in the keyframe (where mining placed
    it if it did not fire there).
    """
    if not data.bank_arrays:
        return np.zeros((0, 4)), np.zeros(0)
    bank = Bank.from_arrays(data.bank_arrays)
    nominal = np.array([c.nominal_xy for c in bank.classifiers], dtype=float).reshape(-1, 2)
    centres = np.asarray(data.meta.get("detections_at_reference", []), dtype=float).reshape(-1, 2)
    if len(centres) != len(bank):
        centres = nominal
    centres = np.where(np.isfinite(centres), centres, nominal)
    size = np.array([c.box[2:4] for c in bank.classifiers], dtype=float).reshape(-1, 2)
    # detections are window centres in pixel-centre coordinates; boxes are drawn on pixel edges
    boxes = np.concatenate([centres + 0.5 - size / 2, centres + 0.5 + size / 2], axis=1)
    p_cam = transform(invert(store.T_vehicle_camera), data.landmarks) if len(data.landmarks) else np.zeros((0, 3))
    return boxes, p_cam[:, 2]


def place_figure(store: MapStore, index: int, path) -> Path:
    """Keyframe of one place with signature boxes coloured by landmark depth."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    data = store.load_place(index)
    img = data.keyframe_image()
    boxes, depth = _boxes_and_depths(store, data)
    W, H = store.camera.width, store.camera.height
    fig, ax = plt.subplots(figsize=(8, 8 * H / W + 0.6))
    if img is not None:
        ax.imshow(img, cmap="gray", extent=(0, W, H, 0))
    cmap = plt.get_cmap("viridis")
    norm = matplotlib.colors.LogNorm(vmin=2, vmax=100)
    for (x0, y0, x1, y1), d in zip(boxes, depth):
        c = cmap(norm(np.clip(d, 2, 100)))
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=1.5, ec=c))
        ax.text(x0 + 2, y0 + 10, f"{d:.0f} m", color=c, fontsize=7)
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.set_title(f"place {index}: {len(boxes)} scene signatures (colour: landmark depth)")
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, label="depth (m)", fraction=0.03)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def heatmap(store: MapStore, indices, path, cell: int = 8) -> Path:
    """How often each image cell is covered by a signature, over the given places."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    W, H = store.camera.width, store.camera.height
    acc = np.zeros((H // cell + 1, W // cell + 1))
    for i in indices:
        boxes, _ = _boxes_and_depths(store, store.load_place(i))
        for x0, y0, x1, y1 in boxes:
            r0, r1 = int(max(0, y0) // cell), int(min(H - 1, y1) // cell) + 1
            c0, c1 = int(max(0, x0) // cell), int(min(W - 1, x1) // cell) + 1
            acc[r0:r1, c0:c1] += 1
    fig, ax = plt.subplots(figsize=(8, 8 * H / W + 0.6))
    im = ax.imshow(acc / max(1, len(indices)), extent=(0, W, H, 0), cmap="inferno")
    ax.set_title(f"signature coverage over {len(indices)} places")
    fig.colorbar(im, ax=ax, label="signatures per place covering the cell", fraction=0.03)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def overview(store: MapStore, path) -> Path:
    """Places along the route, coloured by number of signatures."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metas = list(store.places.values())
    xy = np.array([p.position[:2] for p in metas]).reshape(-1, 2)
    n = np.array([p.signatures for p in metas])
    fig, ax = plt.subplots(figsize=(7, 6))
    sc = ax.scatter(xy[:, 0], xy[:, 1], c=n, cmap="viridis", s=40)
    for p in metas:
        ax.annotate(str(p.index), p.position[:2], fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("places (colour: scene signatures)")
    fig.colorbar(sc, ax=ax, label="signatures")
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def show_map(map_dir, out, place: int | None = None, progress: bool = True) -> list[Path]:
    """Write the map's figures into ``out``; returns their paths.

    Parameters
    ----------
    map_dir : a map folder (``maps/NAME``).
    out : figure folder (created).
    place : only this place's keyframe figure (the heat map then covers that place alone).
    """
    from tqdm import tqdm

    store = MapStore.open(map_dir)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    indices = sorted(store.places)
    if place is not None:
        if place not in store.places:
            raise DataError(store.manifest_path, f"the map has no place {place} (places: "
                                                 f"{indices[0] if indices else '-'}..{indices[-1] if indices else '-'})")
        indices = [place]
    written = [place_figure(store, i, out / f"place_{i:04d}.png")
               for i in tqdm(indices, desc="map show", disable=not progress)]
    written.append(heatmap(store, indices, out / "heatmap.png"))
    written.append(overview(store, out / "places.png"))
    return written


def describe_map(root, place: int | None = None) -> str:
    """The map's generation, its update history and, per place, signatures and experiences (text)."""
    store = MapStore.open(root)
    lines = [f"map {store.root}: {len(store)} places, generation {store.generation}, built from "
             f"{', '.join(store.params.get('runs', []))}"]
    for h in store.history:
        runs = ", ".join(f"{r['run']} ({','.join(r['conditions'])})" for r in h["runs"])
        lines.append(f"  generation {h['generation']}: {runs} -> places {h['places']}")
    for i, m in store.places.items():
        if place is not None and i != place:
            continue
        exps = m.extra.get("experiences", [])
        lines.append(f"place {i:4d}: {m.signatures:3d} signatures, {len(exps)} experience(s)")
        for e in exps:
            lines.append(f"    {e['run']} ({','.join(e['conditions'])}) frame {e['frame']}, generation "
                         f"{e['generation']}, {e['reason']}, +{e['signatures_added']} signatures")
    return "\n".join(lines)
