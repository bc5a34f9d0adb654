"""PAINT flux images (``<ID>-flux.png``, ``<ID>-flux-centered.png``): relative
brightness of the camera image of the spot on the target."""

from __future__ import annotations

import os

import numpy as np
from PIL import Image

from .._errors import DataError
from .._io import input_file_problem

MAX_FLUX_PIXELS = 4096 * 4096
"""Largest image (pixels) read; PAINT's flux images are 512 x 512. A larger
declared size is refused before decoding (a decompression bomb)."""


def read_flux_png(path: str | os.PathLike) -> np.ndarray:
    """A PAINT flux PNG as a float64 ``(rows, cols)`` array in ``[0, 1]``.

    Raises:
        DataError: unreadable or not a PNG (a JPEG named ``.png``), larger than
            :data:`MAX_FLUX_PIXELS`, rotated or mirrored by an EXIF orientation, or
            with transparent pixels, in colour (channels that differ: a false-colour
            rendering is no brightness), or not a regular file (a FIFO blocked the open).
    """
    try:
        problem = input_file_problem(path)
        if problem is not None:
            raise DataError(path, None, problem)
        with Image.open(path) as im:
            w, h = im.size
            if w * h > MAX_FLUX_PIXELS:
                raise DataError(path, None, f"image of {w} x {h} pixels exceeds {MAX_FLUX_PIXELS} pixels")
            if im.format != "PNG":  # Pillow reads by content: a JPEG named .png is lossy and not PAINT's
                raise DataError(path, None, f"is a {im.format or 'non-PNG'} file, not a PNG")
            orientation = im.getexif().get(0x0112, 1)
            if orientation != 1:  # a viewer would show it turned: which way is up is unclear
                raise DataError(path, None, f"EXIF orientation {orientation} (rotated or mirrored) is not supported")
            if im.mode in ("LA", "La", "PA", "RGBA", "RGBa") or "transparency" in im.info:
                alpha = np.asarray(im.convert("RGBA"))[..., 3]
                if alpha.min() < 255:  # a transparent pixel's grey value is no brightness
                    raise DataError(path, None, f"{int((alpha < 255).sum())} pixels are transparent (alpha < 255)")
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit grey: "L" would clip it at 255
                image = np.asarray(im, np.float64)
                if image.min() < 0 or image.max() > 65535:
                    raise DataError(path, None, f"{im.mode} pixel values outside 0..65535")
                return image / 65535.0
            if im.mode not in ("1", "L", "LA", "La", "I;16", "I;16B", "I;16L", "I"):  # palette, RGB, CMYK, ...
                rgb = np.asarray(im.convert("RGB"), np.int16)
                spread = int((rgb.max(axis=-1) - rgb.min(axis=-1)).max())
                if spread > 0:  # "L" would weigh the channels into a luminance of a colour map
                    why = f"a colour image ({im.mode}; channels differ by up to {spread}), not grey"
                    raise DataError(path, None, why)
            return np.asarray(im.convert("L"), np.float64) / 255.0
    except DataError:
        raise
    except (OSError, Image.DecompressionBombError, ValueError) as e:
        raise DataError(path, None, f"cannot read PNG: {e}") from e


__all__ = ["MAX_FLUX_PIXELS", "read_flux_png"]
