"""Uncompressed camera frames (ROS ``sensor_msgs/msg/Image``, ``foxglove.RawImage``) →
lossless PNG, and compressed-image format strings → ``jpeg`` / ``png``.

The replay works on encoded frames (the ``.rrd`` logs the recorded bytes of a compressed
frame, never re-encoded). An uncompressed frame has no such bytes, so it is converted once,
losslessly, to PNG: 8-bit images keep every value; ``mono16`` / ``16UC1`` is scaled to 8 bits
(see :func:`raw_to_png`); colour stays colour (BGR); Bayer mosaics are demosaiced with OpenCV
``cvtColor`` (``COLOR_Bayer*2BGR``, with cv_bridge's mapping of ROS pattern names to
OpenCV's). The pipeline then decodes the PNG to grey like any recorded frame; an image whose
three channels are equal gives exactly its grey values.
"""

from __future__ import annotations

import cv2
import numpy as np

#: ROS encoding → (channels, numpy dtype, cvtColor code to BGR or None).
_BAYER = {  # cv_bridge's mapping (ROS names the first row, OpenCV the second)
    "bayer_rggb8": cv2.COLOR_BayerBG2BGR,
    "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
    "bayer_gbrg8": cv2.COLOR_BayerGR2BGR,
    "bayer_grbg8": cv2.COLOR_BayerGB2BGR,
}
_ENCODINGS = {
    "mono8": (1, np.uint8, None),
    "8uc1": (1, np.uint8, None),
    "mono16": (1, np.uint16, None),
    "16uc1": (1, np.uint16, None),
    "bgr8": (3, np.uint8, None),
    "8uc3": (3, np.uint8, None),
    "rgb8": (3, np.uint8, cv2.COLOR_RGB2BGR),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2BGR),
    "8uc4": (4, np.uint8, cv2.COLOR_BGRA2BGR),
    "rgba8": (4, np.uint8, cv2.COLOR_RGBA2BGR),
    **{name: (1, np.uint8, code) for name, code in _BAYER.items()},
    **{name.replace("8", "16"): (1, np.uint16, code) for name, code in _BAYER.items()},
}
#: Encodings :func:`raw_to_png` accepts (ROS ``sensor_msgs/image_encodings`` names).
RAW_ENCODINGS = tuple(sorted(k for k in _ENCODINGS if not k[0].isdigit()))


class ImageEncodingError(ValueError):
    """An uncompressed frame that cannot be converted (unknown encoding, wrong size)."""


def raw_to_pixels(encoding: str, width: int, height: int, step: int, data: bytes, big_endian: bool = False) -> np.ndarray:
    """The frame as an 8-bit grey (H, W) or BGR (H, W, 3) array.

    16-bit images are scaled by 255 / (their largest value) to 8 bits (a 10- or 12-bit sensor
    in a 16-bit container would otherwise be almost black); the scale is per frame.
    Raises :class:`ImageEncodingError` naming the problem.
    """
    key = encoding.strip().lower()
    if key not in _ENCODINGS:
        raise ImageEncodingError(
            f"image encoding {encoding!r} is not supported; supported: {', '.join(RAW_ENCODINGS)}"
        )
    channels, dtype, code = _ENCODINGS[key]
    itemsize = np.dtype(dtype).itemsize
    row = width * channels * itemsize
    if width <= 0 or height <= 0:
        raise ImageEncodingError(f"{encoding} image of {width}x{height} px is empty")
    if step < row:
        raise ImageEncodingError(f"{encoding} image row step {step} B is shorter than a row of {width} px ({row} B)")
    if len(data) < step * (height - 1) + row:
        raise ImageEncodingError(
            f"{encoding} image of {width}x{height} px with step {step} B needs "
            f"{step * (height - 1) + row} B, got {len(data)} B"
        )
    buf = np.frombuffer(data, np.uint8, count=step * (height - 1) + row)
    rows = np.lib.stride_tricks.as_strided(buf, shape=(height, row), strides=(step, 1))
    pixels = np.ascontiguousarray(rows).view(np.dtype(dtype).newbyteorder(">" if big_endian else "<"))
    pixels = pixels.astype(dtype).reshape(height, width, channels) if channels > 1 else pixels.astype(dtype).reshape(height, width)
    if dtype == np.uint16:
        if code is not None:  # demosaic at 16 bits, then scale
            pixels = cv2.cvtColor(pixels, code)
            code = None
        peak = int(pixels.max())
        pixels = (
            np.zeros(pixels.shape, np.uint8)
            if peak == 0
            else np.clip(np.rint(pixels.astype(np.float64) * (255.0 / peak)), 0, 255).astype(np.uint8)
        )
    if code is not None:
        pixels = cv2.cvtColor(pixels, code)
    return pixels


def raw_to_png(encoding: str, width: int, height: int, step: int, data: bytes, big_endian: bool = False) -> bytes:
    """The frame as lossless PNG bytes (see :func:`raw_to_pixels`)."""
    pixels = raw_to_pixels(encoding, width, height, step, data, big_endian)
    ok, png = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ImageEncodingError(f"{encoding} image of {width}x{height} px could not be encoded as PNG")
    return png.tobytes()


def compressed_format(text: str) -> str:
    """``jpeg`` or ``png`` for a compressed image's format string, else the string as given.

    Accepts Foxglove's (``jpeg``, ``png``, ``jpg``) and ROS ``image_transport``'s forms
    (``jpeg``, ``bgr8; jpeg compressed bgr8``, ``rgb8; png compressed rgb8``); a depth image
    (``compressedDepth``) is not a camera frame and keeps its text (the replay refuses it).
    """
    lowered = text.strip().lower()
    if "compresseddepth" in lowered:
        return text
    words = lowered.replace(";", " ").split()
    if "jpeg" in words or "jpg" in words:
        return "jpeg"
    if "png" in words:
        return "png"
    return text
