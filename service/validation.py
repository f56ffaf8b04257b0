"""Check an upload before it is queued, so bad input is a 4xx now instead of a failed job later.

The input is checked with core.capture.probe, which applies `load_capture`'s limits and rules
to what the headers say (sizes, frame counts, decompression bombs, codecs, depth/pose shapes,
a first depth map without valid pixels) and decodes at most one video frame, never the
capture: a small file declaring thousands of HD frames costs the API nothing. The worker
decodes the capture once and enforces the limits again while decoding.
"""
from __future__ import annotations

from pathlib import Path

from core.camera import CameraError
from core.capture.base import CaptureError
from jobs.errors import error_code_of
from service.errors import ApiError, InvalidInput, PayloadTooLarge, UnsupportedMedia

# sniffed format -> file suffix the engine's loader dispatches on (formats it cannot decode
# are absent and refused with 415)
IMAGE_SUFFIX = {"png": ".png", "jpeg": ".jpg", "webp": ".webp", "bmp": ".bmp", "tiff": ".tiff"}
VIDEO_SUFFIX = {"mp4": ".mp4", "matroska": ".mkv", "avi": ".avi"}
GIF_SUFFIX = ".gif"  # an image by its magic bytes, decoded as a (possibly animated) video
DEPTH_SUFFIX = {"npz": ".npz", "npy": ".npy", "exr": ".exr", "png": ".png"}
SNIFF_BYTES = 64


def _head(path: Path) -> bytes:
    with open(path, "rb") as f:
        return f.read(SNIFF_BYTES)


def classify_input(path: Path) -> tuple[str, str]:
    """(kind 'image'|'video'|'capture', suffix) from the file's magic bytes (a zip is a
    nerfstudio capture: transforms.json + images); raises a 4xx ApiError."""
    from core.io.sniff import ZIP_MAGIC, sniff_image, sniff_video  # noqa: PLC0415 — core.io.sniff pulls in av, cv2, OpenEXR, PIL: imported when used

    head = _head(path)
    if not head:
        raise InvalidInput("form field 'file' is empty (0 bytes)", code="empty")
    if head.startswith(ZIP_MAGIC):
        return "capture", ".zip"
    image, video = sniff_image(head), sniff_video(head)
    if image == "gif":
        return "video", GIF_SUFFIX
    if image in IMAGE_SUFFIX:
        return "image", IMAGE_SUFFIX[image]
    if video in VIDEO_SUFFIX:
        return "video", VIDEO_SUFFIX[video]
    if image or video:
        raise UnsupportedMedia(f"'file' is {image or video}, which is not supported; use PNG/JPEG/WebP/BMP/TIFF "
                               "images, MP4/MOV/MKV/WebM/AVI/GIF videos or a nerfstudio capture zip",
                               code="unsupported_format")
    raise UnsupportedMedia("'file' is not an image, a video or a capture zip (unrecognised content)", code="not_media")


def classify_depth(path: Path) -> str:
    from core.io.sniff import sniff_depth  # noqa: PLC0415 — core.io.sniff pulls in av, cv2, OpenEXR, PIL: imported when used

    head = _head(path)
    if not head:
        raise InvalidInput("form field 'depth' is empty (0 bytes)", code="empty")
    kind = sniff_depth(head)
    if kind is None:
        raise UnsupportedMedia("'depth' must be .npz/.npy (array 'depth'), OpenEXR or a 16-bit PNG in millimetres",
                               code="not_depth")
    return DEPTH_SUFFIX[kind]


def media_error_to_api(exc) -> ApiError:
    status = getattr(exc, "http_status", 422)
    cls = {413: PayloadTooLarge, 415: UnsupportedMedia}.get(status, InvalidInput)
    return cls(str(exc), code=exc.code)


def check_capture(input_path: Path, depth_path: Path | None, params) -> dict:
    """Check the capture as the worker will load it, from its headers; returns a short summary
    or raises a 4xx ApiError."""
    from core.capture.probe import probe_capture  # noqa: PLC0415 — core.capture.probe pulls in av, cv2, OpenEXR, PIL: imported when used
    from core.io.limits import MediaError, MediaLimits  # noqa: PLC0415 — core.io.limits pulls in av, cv2, OpenEXR, PIL: imported when used

    try:
        header = probe_capture(input_path, depth_path, params, MediaLimits.from_env())
    except MediaError as exc:
        raise media_error_to_api(exc) from None
    except (CaptureError, CameraError) as exc:
        raise InvalidInput(str(exc), code=error_code_of(exc)) from None
    return {"frames": header.frames, "width": header.width, "height": header.height}
