"""training/lightstage/png.py, the small PNG writer of the contact sheets and the demo clip: its
bytes decode with Pillow, an independent decoder, and read back with its own reader."""

import numpy as np
from PIL import Image

from training.lightstage.png import read_png, write_png


def test_png_round_trip(tmp_path):
    img = np.random.default_rng(0).integers(0, 256, (7, 11, 3), dtype=np.uint8)
    write_png(tmp_path / "x.png", img)
    with Image.open(tmp_path / "x.png") as im:
        assert im.mode == "RGB" and im.size == (11, 7)
        np.testing.assert_array_equal(np.asarray(im), img)
    np.testing.assert_array_equal(read_png(tmp_path / "x.png"), img)
