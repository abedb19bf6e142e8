"""Loading scans and photos: JPEG, PNG, TIFF (8 or 16 bit), EXIF orientation honoured.

``load_image(path) -> (gray, color)``: ``gray`` is float32 in 0..1 (luminance, full bit
depth kept), ``color`` is uint8 BGR (for the QA overlay and glare detection). Images up
to 50 MP are supported; anything the decoders cannot read, a file with no image content
(uniform) or a file type we do not handle raises :class:`calib.errors.UserError` with the
cause.
"""
from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import cv2
import numpy as np

from calib.errors import UserError

#: File signatures of the formats we read (magic bytes -> name).
_MAGIC = ((b"\xff\xd8\xff", "JPEG"), (b"\x89PNG\r\n\x1a\n", "PNG"),
          (b"II*\x00", "TIFF"), (b"MM\x00*", "TIFF"))
#: Largest image accepted (pixels). The issue asks for 50 MP; a little headroom.
MAX_PIXELS = 64_000_000
#: A picture whose luminance spread (98th - 2nd percentile) is below this is "blank".
_BLANK_SPREAD = 0.02


def _quiet_imdecode(buf, flags):
    """cv2.imdecode without OpenCV's own WARN/ERROR lines on stderr: a corrupt file must
    give the user our one-line error, not decoder chatter. libpng writes its errors
    ("libpng error: PNG input buffer is incomplete") to file descriptor 2 itself, past
    OpenCV's log level, so that descriptor points at /dev/null while the decoder runs."""
    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        with _stderr_fd_silenced():
            return cv2.imdecode(buf, flags)
    finally:
        log.setLogLevel(level)


@contextlib.contextmanager
def _stderr_fd_silenced():
    """Point file descriptor 2 at /dev/null for the block (C libraries' own messages);
    Python's sys.stderr is flushed first so nothing written before is lost."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield                       # no descriptor 2 to silence (embedded interpreters)
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def sniff_format(head: bytes) -> str | None:
    """Format name from the first bytes of a file, or None if not JPEG/PNG/TIFF."""
    for magic, name in _MAGIC:
        if head.startswith(magic):
            return name
    return None


def jpeg_chroma_subsampled(path) -> bool:
    """True when ``path`` is a JPEG whose colour (Cb, Cr) is stored at a lower resolution
    than its luminance (4:2:0 or 4:2:2: phones and most scanners' JPEG), read from the
    frame header's sampling factors (ITU T.81 B.2.2); False for anything else or a header
    that cannot be read (the caller then treats the colour as full resolution)."""
    try:
        with open(path, "rb") as f:
            data = f.read(1 << 20)
    except OSError:
        return False
    if not data.startswith(b"\xff\xd8"):
        return False
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return False
        marker = data[i + 1]
        if marker == 0xFF:                       # fill byte
            i += 1
            continue
        length = int.from_bytes(data[i + 2:i + 4], "big")
        # SOF0-SOF15 except DHT (C4), JPG (C8) and DAC (CC)
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            n = data[i + 9] if i + 9 < len(data) else 0
            comps = [data[i + 11 + 3 * k] for k in range(n) if i + 11 + 3 * k < len(data)]
            if n != 3 or len(comps) != 3:
                return False
            h = [c >> 4 for c in comps]
            v = [c & 15 for c in comps]
            return h[0] > max(h[1:]) or v[0] > max(v[1:])
        if marker == 0xDA:                       # start of scan: no frame header before it
            return False
        i += 2 + length
    return False


def load_image(path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``path`` and return ``(gray float32 0..1 (H, W), color uint8 BGR (H, W, 3))``.

    EXIF orientation is applied (OpenCV's decoder does it unless told not to), so the
    arrays are the picture as a viewer shows it. 16-bit images keep their depth in
    ``gray``. Raises UserError for a missing, unsupported, corrupt, too large or blank file.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise UserError(f"image {path} does not exist") from None
    except IsADirectoryError:
        raise UserError(f"image {path} is a folder, not an image file") from None
    except OSError as exc:
        raise UserError(f"cannot read image {path}: {exc.strerror or exc}") from None
    if not data:
        raise UserError(f"image {path} is an empty file (0 bytes); scan or photograph the print again")
    fmt = sniff_format(data[:16])
    if fmt is None:
        raise UserError(f"image {path} is not a JPEG, PNG or TIFF file; export the scan as one of those")
    buf = np.frombuffer(data, dtype=np.uint8)
    # IMREAD_ANYDEPTH keeps 16 bit; IMREAD_COLOR applies EXIF orientation.
    img = _quiet_imdecode(buf, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise UserError(f"image {path} is a corrupt or truncated {fmt} file; copy or export it again")
    h, w = img.shape[:2]
    if h * w > MAX_PIXELS:
        raise UserError(f"image {path} has {h * w / 1e6:.0f} MP, more than the {MAX_PIXELS // 1_000_000} MP "
                        "supported; scan at a lower resolution (600-1200 dpi is plenty)")
    if img.dtype == np.uint16:
        scale = 65535.0
    elif img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype in (np.float32, np.float64):
        scale = 1.0
    else:
        raise UserError(f"image {path} has pixel type {img.dtype}, which is not supported; "
                        "save it as 8- or 16-bit")
    gray = cv2.cvtColor(img.astype(np.float32) / np.float32(scale), cv2.COLOR_BGR2GRAY)
    color = img if img.dtype == np.uint8 else np.clip(img.astype(np.float32) / scale * 255.0 + 0.5,
                                                     0, 255).astype(np.uint8)
    # Percentiles on a subsample: cheap on 50 MP and robust to a few hot pixels.
    step = max(1, int(np.sqrt(h * w / 1e6)))
    lo, hi = np.percentile(gray[::step, ::step], [2, 98])
    if hi - lo < _BLANK_SPREAD:
        raise UserError(f"image {path} is blank (uniform grey level {float(np.median(gray[::step, ::step])):.2f}); "
                        "check the scan shows the printed pattern")
    return np.ascontiguousarray(gray, dtype=np.float32), np.ascontiguousarray(color)
