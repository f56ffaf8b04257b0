"""MediaLimits / MediaError contracts and content sniffing (never by file name)."""
import io

import numpy as np
import pytest
from PIL import Image

from core.io import HTTP_STATUS, MediaError, MediaLimits, sniff_depth, sniff_media, write_video
from core.io.sniff import sniff_hdr_image


def test_limits_from_env_overrides_only_given_fields():
    limits = MediaLimits.from_env(
        {"LIGHTFIELD_MAX_BYTES": "1000", "LIGHTFIELD_MAX_FRAMES": "7", "LIGHTFIELD_MAX_PIXELS": ""}
    )
    assert limits.max_bytes == 1000 and limits.max_frames == 7
    assert limits.max_pixels == MediaLimits().max_pixels


def test_limits_from_env_names_the_bad_variable():
    with pytest.raises(ValueError, match="LIGHTFIELD_MAX_PIXELS"):
        MediaLimits.from_env({"LIGHTFIELD_MAX_PIXELS": "lots"})
    with pytest.raises(ValueError, match="max_frames"):
        MediaLimits(max_frames=0)


def test_media_error_codes_map_to_client_errors():
    assert all(400 <= status < 500 for status in HTTP_STATUS.values())
    err = MediaError("too_large", "x")
    assert isinstance(err, ValueError) and err.code == "too_large" and err.http_status == 413
    with pytest.raises(ValueError):
        MediaError("no_such_code", "x")


def _pil_bytes(fmt: str) -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (8, 8), (10, 20, 30)).save(buf, format=fmt)
    return buf.getvalue()


@pytest.mark.parametrize("fmt", ["PNG", "JPEG", "WEBP", "BMP", "TIFF", "GIF"])
def test_images_are_sniffed_from_content(fmt):
    data = _pil_bytes(fmt)
    assert sniff_media(data) == "image"
    assert sniff_depth(data) == ("png" if fmt == "PNG" else None)


def test_video_containers_are_sniffed_from_content(tmp_path):
    path = write_video(tmp_path / "clip.mp4", np.zeros((2, 16, 16, 3), np.float32), 10)
    assert sniff_media(path.read_bytes()) == "video"
    assert sniff_media(b"\x1a\x45\xdf\xa3" + bytes(28)) == "video"  # WebM / Matroska EBML
    assert sniff_media(b"RIFF\x00\x00\x00\x00AVI LIST") == "video"
    # an ISO-BMFF still image (HEIC/AVIF) is not a video even though it has an ftyp box
    assert sniff_media(b"\x00\x00\x00\x18ftypavif\x00\x00\x00\x00") == "image"


@pytest.mark.parametrize("data", [b"", b"hello world, not media", bytes(64), b"GIF", b"\x89PN"])
def test_unknown_content_is_not_media(data):
    assert sniff_media(data) is None
    assert sniff_depth(data) is None
    assert sniff_hdr_image(data) is None


def test_depth_and_hdr_containers_are_sniffed():
    buf = io.BytesIO()
    np.savez(buf, depth=np.ones((2, 2)))
    assert sniff_depth(buf.getvalue()) == "npz"
    buf = io.BytesIO()
    np.save(buf, np.ones((2, 2)))
    assert sniff_depth(buf.getvalue()) == "npy" and sniff_hdr_image(buf.getvalue()) == "npy"
    assert sniff_hdr_image(b"#?RADIANCE\n") == "hdr"
    assert sniff_depth(b"\x76\x2f\x31\x01rest") == "exr"
