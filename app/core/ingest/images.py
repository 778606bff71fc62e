"""Image checks: a JPEG or PNG is sized from its header and decoded within limits before it
is kept (decompression bombs are refused without decoding them)."""

from __future__ import annotations

import struct
import zlib
from typing import BinaryIO

from PIL import Image, UnidentifiedImageError

from app.core.errors import (
    DomainError,
)
from app.core.ingest.common import IMAGE_FORMATS, _invalid, _reason, _too_large


def probe_image(
    source: BinaryIO, where: str, max_pixels: int, max_decoded_bytes: int | None = None
) -> tuple[int, int]:
    """Width and height of a JPEG or PNG after checking that it decodes.

    The pixel count and the decoded size (width × height × channels × bytes per sample, at
    least 3 bytes a pixel: readers decode to 8-bit colour) come from the header
    (``Image.open`` reads nothing else) and are checked against ``max_pixels`` and
    ``max_decoded_bytes`` before any decoding; JPEGs decode at 1/8 scale (``Image.draft``);
    PNGs are verified (chunk CRCs) and their pixel stream inflated in pieces and counted, so
    memory stays small whatever the size. ``ImageTooLarge`` (413) or ``InvalidImage`` (422);
    details never show server paths.
    """
    try:
        with Image.open(source) as img:
            fmt = img.format
            width, height = img.size
            if fmt not in IMAGE_FORMATS:
                raise _invalid("InvalidImage", f"{where}: not a JPEG or PNG image ({fmt})")
            _check_pixels(width, height, where, max_pixels)
            if max_decoded_bytes is not None:
                per_pixel = _png_pixel_bytes(source) if fmt == "PNG" else len(img.getbands())
                _check_decoded(width, height, max(3, per_pixel), where, max_decoded_bytes)
            if fmt == "JPEG":
                img.draft(img.mode, (max(1, width // 8), max(1, height // 8)))
                img.load()
            else:
                img.verify()
        if fmt == "PNG":
            _check_png_pixels(source, where)
    except Image.DecompressionBombError as exc:
        raise _too_large("ImageTooLarge", f"{where}: {_reason(exc)}") from exc
    except DomainError:
        raise
    except (
        UnidentifiedImageError,
        OSError,
        SyntaxError,
        ValueError,
        EOFError,
        struct.error,
        zlib.error,
    ) as exc:
        raise _invalid(
            "InvalidImage", f"{where}: not a readable JPEG or PNG ({_reason(exc)})"
        ) from exc
    return width, height


# A file object's repr (``<_io.BufferedReader name='/srv/...'>``) or an absolute path.


def _png_pixel_bytes(source: BinaryIO) -> int:
    """Bytes a decoded pixel takes, from the PNG's IHDR (channels × bytes per sample;
    palette images decode to RGBA)."""
    at = source.tell()
    source.seek(16)
    head = source.read(10)
    source.seek(at)
    if len(head) < 10:
        return 4
    depth, color = head[8], head[9]
    channels = 4 if color == 3 else _PNG_CHANNELS.get(color, 4)
    return channels * (2 if depth > 8 else 1)


def _check_decoded(width: int, height: int, per_pixel: int, where: str, limit: int) -> None:
    decoded = width * height * per_pixel
    if decoded > limit:
        raise _too_large(
            "ImageTooLarge",
            f"{where}: {width}×{height} at {per_pixel} bytes a pixel decodes to {decoded} "
            f"bytes, more than the limit of {limit}",
        )


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
_ADAM7 = (
    (0, 0, 8, 8),
    (4, 0, 8, 8),
    (0, 4, 4, 8),
    (2, 0, 4, 4),
    (0, 2, 2, 4),
    (1, 0, 2, 2),
    (0, 1, 1, 2),
)


def _png_raw_size(width: int, height: int, bit_depth: int, color_type: int, interlace: int) -> int:
    """Bytes of the filtered scanlines a PNG header promises (PNG spec, section 7-8)."""
    bits = _PNG_CHANNELS.get(color_type, 4) * bit_depth
    passes = _ADAM7 if interlace else ((0, 0, 1, 1),)
    total = 0
    for x0, y0, dx, dy in passes:
        w, h = -(-(width - x0) // dx), -(-(height - y0) // dy)
        if w > 0 and h > 0:
            total += h * (1 + (w * bits + 7) // 8)
    return total


def _check_png_pixels(source: BinaryIO, where: str) -> None:
    """Inflate a PNG's IDAT stream piece by piece and check it holds exactly the scanline
    bytes its header promises (the chunk CRCs were checked by ``verify``)."""
    source.seek(8)
    inflater = zlib.decompressobj()
    expected, produced = 0, 0
    while True:
        head = source.read(8)
        if len(head) < 8:
            raise _invalid("InvalidImage", f"{where}: truncated PNG")
        length, kind = struct.unpack(">I4s", head)
        if kind == b"IHDR":
            width, height, depth, color, _, _, interlace = struct.unpack(
                ">IIBBBBB", source.read(13)
            )
            expected = _png_raw_size(width, height, depth, color, interlace)
            source.seek(length - 13, 1)
        elif kind == b"IDAT":
            left = length
            while left:
                piece = source.read(min(left, 1024 * 1024))
                if not piece:
                    raise _invalid("InvalidImage", f"{where}: truncated PNG")
                left -= len(piece)
                while piece:
                    produced += len(inflater.decompress(piece, 1024 * 1024))
                    piece = inflater.unconsumed_tail
                    if produced > expected:
                        raise _invalid("InvalidImage", f"{where}: more pixel data than its size")
        elif kind == b"IEND":
            break
        else:
            source.seek(length, 1)
        source.seek(4, 1)  # the CRC
    if not inflater.eof or produced != expected:
        raise _invalid(
            "InvalidImage", f"{where}: pixel data ends early ({produced} of {expected} bytes)"
        )


def _check_pixels(width: int, height: int, where: str, max_pixels: int) -> None:
    if width <= 0 or height <= 0:
        raise _invalid("InvalidImage", f"{where}: empty image ({width}×{height})")
    if width * height > max_pixels:
        raise _too_large(
            "ImageTooLarge",
            f"{where}: {width}×{height} = {width * height} pixels, more than the limit "
            f"of {max_pixels}",
        )
