"""File metadata honoured: EXIF orientation and focal length, ICC colour profiles, video rotation."""
from __future__ import annotations

import io
import math
import struct

import numpy as np
import pytest
from PIL import ExifTags, Image, ImageOps

from core.io.images import decode_image, read_image
from core.io.metadata import ImageMetadata, exif_intrinsics, image_metadata, orient_array
from core.io.video import read_video, write_video

# Display P3 (what iPhones tag their photos with): D50-adapted colorants of Apple's profile.
P3_D50 = np.array([[0.5151, 0.2920, 0.1571], [0.2412, 0.6922, 0.0666], [-0.0011, 0.0419, 0.7841]])
SRGB_D50 = np.array([[0.4361, 0.3851, 0.1431], [0.2225, 0.7169, 0.0606], [0.0139, 0.0971, 0.7141]])
D50 = (0.9642, 1.0, 0.8249)


def _s15(x: float) -> bytes:
    return struct.pack(">i", round(x * 65536))


def matrix_trc_profile(colorants: np.ndarray, gamma: float, name: str) -> bytes:
    """A minimal ICC v2 RGB display profile (matrix + gamma TRC), as cameras embed."""
    def xyz(v):
        return b"XYZ " + b"\0" * 4 + b"".join(_s15(c) for c in v)
    desc_text = name.encode("ascii") + b"\0"
    desc = b"desc" + b"\0" * 4 + struct.pack(">I", len(desc_text)) + desc_text + b"\0" * 12 + b"\0" * 3 + b"\0" * 67
    curve = b"curv" + b"\0" * 4 + struct.pack(">IH", 1, round(gamma * 256)) + b"\0" * 2
    tags = [(b"desc", desc), (b"wtpt", xyz(D50)), (b"rXYZ", xyz(colorants[:, 0])), (b"gXYZ", xyz(colorants[:, 1])),
            (b"bXYZ", xyz(colorants[:, 2])), (b"rTRC", curve), (b"gTRC", curve), (b"bTRC", curve),
            (b"cprt", b"text" + b"\0" * 4 + b"CC0\0")]
    offset = 128 + 4 + 12 * len(tags)
    table, body = b"", b""
    for sig, data in tags:
        data += b"\0" * (-len(data) % 4)
        table += sig + struct.pack(">II", offset + len(body), len(data))
        body += data
    size = offset + len(body)
    header = (struct.pack(">I", size) + b"lcms" + struct.pack(">I", 0x02100000) + b"mntrRGB XYZ " + b"\0" * 12 + b"acsp"
              + b"APPL" + b"\0" * 4 + b"\0" * 8 + b"\0" * 8 + struct.pack(">I", 0) + b"".join(_s15(c) for c in D50)
              + b"lcms" + b"\0" * 44)
    assert len(header) == 128
    return header + struct.pack(">I", len(tags)) + table + body


def _asymmetric(h=16, w=24) -> np.ndarray:
    a = np.zeros((h, w, 3), np.uint8)
    a[..., 0] = np.arange(w)[None, :] * 10
    a[..., 1] = np.arange(h)[:, None] * 15
    a[:3, :5, 2] = 255
    return a


def _encode(a: np.ndarray, fmt: str, exif: Image.Exif | None = None, **kw) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, fmt, **({"exif": exif} if exif is not None else {}), **kw)
    return buf.getvalue()


@pytest.mark.parametrize("orientation", range(1, 9))
def test_orient_array_matches_pillows_exif_transpose(orientation):
    a = _asymmetric()
    ex = Image.Exif()
    ex[ExifTags.Base.Orientation] = orientation
    img = Image.open(io.BytesIO(_encode(a, "PNG", ex)))
    want = np.asarray(ImageOps.exif_transpose(img))
    assert np.array_equal(orient_array(a, orientation), want)
    assert np.array_equal(np.round(read_image(_encode(a, "PNG", ex)) * 255).astype(np.uint8), want)


def test_sideways_jpeg_decodes_like_its_upright_twin():
    upright = (np.random.default_rng(0).uniform(0, 255, (48, 64, 3))).astype(np.uint8)
    stored = np.rot90(upright, 1).copy()  # what the phone stored; orientation 6 = rotate 90 cw to view
    ex = Image.Exif()
    ex[ExifTags.Base.Orientation] = 6
    sideways = decode_image(_encode(stored, "JPEG", ex, quality=100, subsampling=0))
    twin = read_image(_encode(upright, "JPEG", quality=100, subsampling=0))
    assert sideways.pixels.shape == twin.shape == (48, 64, 3)
    assert sideways.stored_size == (48, 64)
    assert np.abs(sideways.pixels - twin).max() <= 4 / 255  # JPEG IDCT rounding only
    assert any("orientation 6" in a for a in sideways.applied)


def test_exif_focal_length_35mm_equivalent_gives_the_phones_field_of_view():
    ex = Image.Exif()
    ex.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = 26  # an iPhone main camera
    ex.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLength] = 5.7
    meta = image_metadata(Image.open(io.BytesIO(_encode(_asymmetric(), "JPEG", ex))))
    assert meta.focal_length_35mm == 26 and meta.focal_length_mm == pytest.approx(5.7)
    k, rule = exif_intrinsics(meta, 4032, 3024)
    # diagonal crop factor: fx = 26 mm * 5040 px / 43.27 mm
    assert k.fx == pytest.approx(26 * 5040 / math.hypot(36, 24)) and k.fx == k.fy
    assert (k.cx, k.cy) == (2016, 1512)
    assert 67 < k.hfov_deg < 68.5 and "FocalLengthIn35mmFilm" in rule
    portrait, _ = exif_intrinsics(meta, 3024, 4032)  # the same lens, upright portrait
    assert portrait.fx == pytest.approx(k.fx)


def test_exif_focal_plane_resolution_is_rescaled_to_the_stored_width():
    meta = ImageMetadata(focal_length_mm=4.0, focal_plane_px_per_mm=1000.0, exif_width=4000)
    k, rule = exif_intrinsics(meta, 1000, 750)  # the file was downscaled 4x
    assert k.fx == pytest.approx(4.0 * 1000.0 / 4)
    assert "resized" in rule
    assert exif_intrinsics(ImageMetadata(focal_length_mm=4.0), 100, 75) is None  # mm alone cannot be converted


def test_display_p3_profile_is_converted_to_srgb():
    p3 = matrix_trc_profile(P3_D50, 2.2, "Display P3 test")
    colours = np.array([[[200, 60, 40], [90, 180, 70], [128, 128, 128], [40, 80, 210]]], np.uint8)
    decoded = decode_image(_encode(colours, "PNG", icc_profile=p3))
    assert decoded.metadata.icc_description == "Display P3 test" and decoded.metadata.icc_is_srgb is False
    assert any("to sRGB" in a for a in decoded.applied)
    lin = (colours[0] / 255.0) ** 2.2
    srgb_lin = np.clip(lin @ P3_D50.T @ np.linalg.inv(SRGB_D50).T, 0, 1)
    srgb = np.where(srgb_lin <= 0.0031308, 12.92 * srgb_lin, 1.055 * srgb_lin ** (1 / 2.4) - 0.055)
    assert np.abs(decoded.pixels[0] - srgb).max() < 4 / 255
    assert np.abs(decoded.pixels[0] - colours[0] / 255.0).max() > 10 / 255  # it did change


def test_srgb_and_broken_profiles_leave_pixels_alone():
    from PIL import ImageCms

    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    a = _asymmetric()
    tagged = decode_image(_encode(a, "PNG", icc_profile=srgb))
    assert tagged.metadata.icc_is_srgb and not tagged.applied
    assert np.array_equal(np.round(tagged.pixels * 255).astype(np.uint8), a)
    broken = decode_image(_encode(a, "PNG", icc_profile=b"not a profile at all" * 10))
    assert broken.metadata.icc_error and np.array_equal(np.round(broken.pixels * 255).astype(np.uint8), a)


@pytest.mark.parametrize("ccw", [0, 90, -90, 180])
def test_video_display_rotation_is_applied(tmp_path, ccw):
    a = np.zeros((3, 16, 32, 3), np.uint8)
    a[:, :4, :8] = 255  # a bright block at the stored top-left
    path = write_video(tmp_path / "phone.mp4", a, 10, display_rotation_ccw=ccw)
    v = read_video(path)
    assert v.rotation_ccw_deg == ccw % 360
    want = np.rot90(a[0].mean(-1), (ccw // 90) % 4)  # what a player shows
    got = v.frames[0].mean(-1) * 255
    assert got.shape == want.shape
    assert np.abs(got - want).mean() < 12  # H.264 blurs the edges of the block
