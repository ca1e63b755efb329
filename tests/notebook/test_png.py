"""leglib.notebook.png: the panels' and the live view's PNG writer decodes, in another
reader (Pillow), to exactly the pixels it was given."""

import io

import numpy as np
import pytest
from PIL import Image

from leglib.errors import ArgumentError
from leglib.notebook import png


@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (380, 1500)])
@pytest.mark.parametrize("level", [0, 1, 9])
def test_opaque_pixels_come_back_exactly_as_rgb(shape, level):
    rng = np.random.default_rng(shape[0] * 31 + level)
    rgba = rng.integers(0, 256, (*shape, 4), dtype=np.uint8)
    rgba[:, :, 3] = 255
    back = Image.open(io.BytesIO(png.encode(rgba, level)))
    assert back.mode == "RGB" and back.size == (shape[1], shape[0])
    assert np.array_equal(np.asarray(back), rgba[:, :, :3])


def test_transparent_pixels_keep_their_alpha():
    rgba = np.random.default_rng(1).integers(0, 256, (5, 9, 4), dtype=np.uint8)
    rgba[0, 0, 3] = 10
    back = Image.open(io.BytesIO(png.encode(rgba)))
    assert back.mode == "RGBA" and np.array_equal(np.asarray(back), rgba)


def test_a_canvas_buffer_is_written_as_a_strided_view():
    """``canvas.buffer_rgba()`` is a memoryview; a sliced (non-contiguous) array works too."""
    rgba = np.zeros((6, 8, 4), np.uint8)
    rgba[..., 3] = 255
    rgba[2:4, 3:5, 0] = 200
    view = rgba[::2, ::2]
    back = np.asarray(Image.open(io.BytesIO(png.encode(memoryview(np.ascontiguousarray(view))))))
    assert np.array_equal(back, view[:, :, :3])
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png.encode(view)))), view[:, :, :3])


@pytest.mark.parametrize("bad, what", [(np.zeros((4, 4, 3), np.uint8), "shape"),
                                       (np.zeros((4, 4, 4), np.float64), "float64"),
                                       (np.zeros((0, 4, 4), np.uint8), "shape")])
def test_bad_pixels_are_named(bad, what):
    with pytest.raises(ArgumentError, match=f"png.encode: rgba .*{what}"):
        png.encode(bad)


def test_a_bad_level_is_named():
    with pytest.raises(ArgumentError, match="level = 10"):
        png.encode(np.zeros((2, 2, 4), np.uint8), 10)
