"""PAINT flux images (``<ID>-flux.png``, ``<ID>-flux-centered.png``): relative
brightness of the camera image of the spot on the target."""

from __future__ import annotations

import os

import numpy as np
from PIL import Image

from .._errors import DataError
from .._io import check_path_argument, input_file_problem

MAX_FLUX_PIXELS = 4096 * 4096
"""Largest image (pixels) read; PAINT's flux images are 512 x 512. A larger
declared size is refused before decoding (a decompression bomb)."""


MIN_FLUX_BITS = 8
"""Fewest bits per sample (or per palette index) of a flux PNG: a camera's flux image
has 8 or 16; one of 1, 2 or 4 bits (mode ``1``, a 2-colour palette) is thresholded
or posterised, and its 2-16 levels are no brightness to compare a traced flux with."""


def _png_bit_depth(path: str | os.PathLike) -> tuple[int, int]:
    """``(bit depth, colour type)`` of a PNG's header (its first chunk, IHDR, by the PNG
    standard; the caller has had Pillow identify the file as a PNG)."""
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) < 26 or head[12:16] != b"IHDR":
        raise DataError(path, None, "cannot read PNG: no IHDR header chunk first")
    return head[24], head[25]


def read_flux_png(path: str | os.PathLike) -> np.ndarray:
    """A PAINT flux PNG as a float64 ``(rows, cols)`` array in ``[0, 1]``.

    Raises:
        TypeError, ValueError: ``path`` is no path (an int was read as a file
            descriptor) or empty (:func:`~heliojax._io.check_path_argument`).
        DataError: unreadable or not a PNG (a JPEG named ``.png``), larger than
            :data:`MAX_FLUX_PIXELS`, of fewer than :data:`MIN_FLUX_BITS` bits per
            sample (mode ``1``), animated, rotated or mirrored by an EXIF orientation, or
            with transparent pixels, in colour (channels that differ: a false-colour
            rendering is no brightness), or not a regular file (a FIFO blocked the open).
    """
    check_path_argument(path)
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
            depth, colour_type = _png_bit_depth(path)
            if depth < MIN_FLUX_BITS:  # a thresholded (1-bit) or posterised spot is no brightness
                kind = "palette" if colour_type == 3 else "grey" if colour_type in (0, 4) else "colour"
                raise DataError(
                    path,
                    None,
                    f"a {depth}-bit {kind} image (mode {im.mode}, at most {2**depth} brightness levels): "
                    f"a flux image needs at least {MIN_FLUX_BITS} bits (256 levels)",
                )
            frames = getattr(im, "n_frames", 1)
            if frames != 1:  # an animated PNG: which frame is the flux image is unclear
                raise DataError(path, None, f"an animated PNG of {frames} frames, not one flux image")
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


__all__ = ["MAX_FLUX_PIXELS", "MIN_FLUX_BITS", "read_flux_png"]
