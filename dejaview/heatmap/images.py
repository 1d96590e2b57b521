"""Heatmap files: ``heatmap.ppm`` (P3), ``heatmap.png`` and their readers.

Orientation follows the scene-format spec: ``probability[j][i]`` is column i
(x, from -x) and row j (y, from -y up); the PPM's rows go from +y down to -y,
columns from -x to +x, one pixel per cell, so an image viewer shows +y up.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

COLORMAP = "viridis"


def colors(probability: np.ndarray) -> np.ndarray:
    """RGB bytes (ny, nx, 3) for a probability grid (ny, nx), rows from -y up.

    Scaled by the largest cell, so the most probable cell takes the top colour.
    """
    from matplotlib import colormaps

    p = np.asarray(probability, dtype=float)
    top = p.max() if p.size and p.max() > 0 else 1.0
    rgba = colormaps[COLORMAP](p / top)
    return np.round(rgba[..., :3] * 255).astype(np.uint8)


def ppm_text(probability: np.ndarray) -> str:
    """PPM P3 text of a probability grid (ny, nx), rows from -y up (flipped to +y first)."""
    rgb = colors(probability)[::-1]
    ny, nx = rgb.shape[:2]
    lines = ["P3", "# DejaView start-position heatmap: rows from +y to -y, columns from -x to +x",
             f"{nx} {ny}", "255"]
    lines += [" ".join(str(int(v)) for v in row.reshape(-1)) for row in rgb]
    return "\n".join(lines) + "\n"


def write_ppm(path, probability: np.ndarray) -> Path:
    """Write ``ppm_text`` to path; returns the path."""
    path = Path(path)
    path.write_text(ppm_text(probability), encoding="ascii")
    return path


def read_ppm(path_or_text) -> np.ndarray:
    """Parse a PPM P3 (a path, or the text itself) into RGB values (height, width, 3).

    Raises:
        ValueError: not a P3 image, or the pixel count does not match the declared size.
    """
    text = path_or_text
    if isinstance(path_or_text, Path) or (isinstance(path_or_text, str) and "\n" not in path_or_text):
        text = Path(path_or_text).read_text(encoding="ascii")
    tokens = []
    for line in text.splitlines():
        tokens += line.split("#", 1)[0].split()
    if not tokens or tokens[0] != "P3":
        raise ValueError("not a PPM P3 image (magic number P3 missing)")
    try:
        width, height, maxval = int(tokens[1]), int(tokens[2]), int(tokens[3])
        values = np.array([int(t) for t in tokens[4:]], dtype=np.int64)
    except (IndexError, ValueError):
        raise ValueError("PPM header or pixel values are not integers") from None
    if width < 1 or height < 1 or not 0 < maxval < 65536:
        raise ValueError(f"bad PPM size {width}x{height} or maximum {maxval}")
    if values.size != width * height * 3:
        raise ValueError(f"PPM declares {width}x{height} pixels but holds {values.size // 3}")
    if values.min(initial=0) < 0 or values.max(initial=0) > maxval:
        raise ValueError(f"PPM values outside 0..{maxval}")
    return values.reshape(height, width, 3)


def write_png(path, probability: np.ndarray, lo, hi, *, truth=None, best=None, title=None) -> Path:
    """``heatmap.png``: the grid over the start area's x-y extent, a colour scale, axes in metres.

    Args:
        path: where to write.
        probability: (ny, nx), rows from -y up.
        lo, hi: (2,) x-y corners of the start area.
        truth: optional (x, y) to mark (e.g. a known true start).
        best: optional (x, y) of the best solution.
        title: optional title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = np.asarray(probability, dtype=float)
    fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=100)
    im = ax.imshow(p, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap=COLORMAP,
                   vmin=0.0, vmax=max(p.max(), 1e-12), interpolation="nearest", aspect="equal")
    fig.colorbar(im, ax=ax, label="probability of the start cell")
    if best is not None:
        ax.plot([best[0]], [best[1]], marker="x", color="red", ms=10, mew=2, ls="", label="best solution")
    if truth is not None:
        ax.plot([truth[0]], [truth[1]], marker="o", mfc="none", color="white", ms=10, mew=2, ls="",
                label="true start")
    if best is not None or truth is not None:
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or "start-position heatmap")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
