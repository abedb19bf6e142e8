"""Image loading: orientation, bit depth, and one clear error per bad file."""
import cv2
import numpy as np
import pytest
from PIL import Image

from calib.errors import UserError
from measure.imageio import load_image


def _scene():
    a = np.full((40, 60, 3), 60, np.uint8)
    a[:10, :20] = 250          # bright block top-left
    return a


def test_exif_orientation_is_applied(tmp_path):
    im = Image.fromarray(_scene())
    ex = im.getexif()
    ex[0x0112] = 6             # "rotate 90 CW to view"
    im.save(tmp_path / "o.jpg", exif=ex, quality=95)
    gray, color = load_image(tmp_path / "o.jpg")
    assert gray.shape == (60, 40) and color.shape == (60, 40, 3)
    # the bright block moved from the top-left to the top-right corner
    assert gray[:8, -8:].mean() > 0.9 and gray[:8, :8].mean() < 0.3


def test_16_bit_tiff_keeps_its_depth(tmp_path):
    ramp = (np.linspace(0, 65535, 64 * 48).reshape(48, 64)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "r.tif"), ramp)
    gray, color = load_image(tmp_path / "r.tif")
    assert gray.dtype == np.float32 and color.dtype == np.uint8
    np.testing.assert_allclose(gray, ramp / 65535.0, atol=1e-6)   # 8-bit would be off by up to 2e-3


def test_png_round_trip(tmp_path):
    cv2.imwrite(str(tmp_path / "s.png"), _scene())
    gray, _ = load_image(tmp_path / "s.png")
    assert gray[0, 0] == pytest.approx(250 / 255, abs=1e-3)


@pytest.mark.parametrize("content, message", [
    (b"", r"is an empty file \(0 bytes\); scan or photograph the print again"),
    (b"GIF89a\x01\x00", "is not a JPEG, PNG or TIFF file"),
    (b"\xff\xd8\xff\xe0" + b"\x00" * 50, "is a corrupt or truncated JPEG file"),
])
def test_bad_files_raise_one_clear_line(tmp_path, content, message):
    p = tmp_path / "bad.jpg"
    p.write_bytes(content)
    with pytest.raises(UserError, match=message):
        load_image(p)


def test_blank_and_missing_images(tmp_path):
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((50, 50), 128, np.uint8))
    with pytest.raises(UserError, match=r"is blank \(uniform grey level 0.50\)"):
        load_image(tmp_path / "blank.png")
    with pytest.raises(UserError, match="does not exist"):
        load_image(tmp_path / "nope.png")


def test_a_truncated_png_says_one_line_and_the_decoder_nothing(tmp_path, capfd):
    """libpng prints "libpng error: ..." on descriptor 2 past OpenCV's log level; the user
    must see our line only. The decoder is quiet only while it runs: descriptor 2 works
    again after the error."""
    noise = (np.random.default_rng(0).random((200, 300, 3)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "s.png"), noise)               # incompressible: many IDAT bytes
    data = (tmp_path / "s.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[:len(data) // 2])
    with pytest.raises(UserError, match="is a corrupt or truncated PNG file"):
        load_image(tmp_path / "cut.png")
    import os
    os.write(2, b"after\n")
    err = capfd.readouterr().err
    assert "libpng" not in err and err == "after\n"
