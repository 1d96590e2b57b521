"""Heatmap files: PPM P3 layout (rows from +y, columns from -x), the reader, the PNG."""

import numpy as np
import pytest

from dejaview.heatmap import read_ppm, write_png, write_ppm
from dejaview.heatmap.images import colors, ppm_text


def test_ppm_is_p3_with_declared_size_and_plus_y_first(tmp_path):
    p = np.zeros((3, 4))  # ny = 3 rows (from -y up), nx = 4 columns
    p[2, 0] = 1.0         # the cell at -x, +y: the image's top-left pixel
    path = write_ppm(tmp_path / "h.ppm", p)
    lines = path.read_text().splitlines()
    assert lines[0] == "P3"
    assert [ln for ln in lines if not ln.startswith("#")][1] == "4 3"
    rgb = read_ppm(path)
    assert rgb.shape == (3, 4, 3)
    top = colors(np.array([[1.0]]))[0, 0]
    low = colors(np.array([[0.0, 1.0]]))[0, 0]
    assert (rgb[0, 0] == top).all()
    assert (rgb[1:, :] == low).all() and (rgb[0, 1:] == low).all()


def test_read_ppm_accepts_text_and_rejects_bad_images():
    text = ppm_text(np.full((2, 2), 0.25))
    assert read_ppm(text).shape == (2, 2, 3)
    with pytest.raises(ValueError, match="P3"):
        read_ppm("P6\n2 2\n255\n" + " 0" * 12 + "\n")
    with pytest.raises(ValueError, match="declares 2x2"):
        read_ppm("P3\n2 2\n255\n0 0 0\n")
    with pytest.raises(ValueError, match="outside"):
        read_ppm("P3\n1 1\n255\n0 0 300\n")
    with pytest.raises(ValueError, match="integers"):
        read_ppm("P3\nx 1\n255\n0 0 0\n")


def test_png_opens_with_the_expected_size(tmp_path):
    import matplotlib.image as mpimg

    p = np.random.default_rng(0).random((5, 6))
    path = write_png(tmp_path / "h.png", p / p.sum(), (-1.0, -0.5), (1.0, 0.5), truth=(0.1, 0.2),
                     best=(0.0, 0.0), title="test")
    img = mpimg.imread(path)
    assert img.shape[0] == 480 and img.shape[1] == 640 and img.shape[2] in (3, 4)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
