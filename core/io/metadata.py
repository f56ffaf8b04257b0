"""What a file says about itself: EXIF orientation and focal length, colour profile, video rotation.

Every value taken from a file is reported (`as_dict`) so the job can list it next to what
was assumed. The rules:

* **Orientation** (EXIF 0x0112, values 1-8): pixels are turned upright exactly as a viewer
  shows them (Pillow's `ImageOps.exif_transpose` table; `orient_array` is the same table on
  arrays, tested against Pillow). Intrinsics, depth and probes refer to the UPRIGHT image.
* **Focal length -> intrinsics** (square pixels, centred principal point), in order:
  1. `FocalLengthIn35mmFilm` (0xA405): the 35 mm equivalent is defined on the diagonal
     (crop factor = 43.27 mm / sensor diagonal), so fx = f35 · sqrt(W² + H²) / 43.27 mm,
     independent of orientation and aspect ratio;
  2. `FocalLength` (0x920A) with `FocalPlaneXResolution`/`FocalPlaneResolutionUnit`
     (0xA20E/0xA210): pixels per mm on the sensor at `PixelXDimension` (0xA002) pixels wide,
     rescaled to the stored width;
  3. neither: no intrinsics from the file (a bare `FocalLength` in mm cannot be converted
     without the sensor size; it is reported, not used).
* **Colour profile**: an embedded ICC profile that is not sRGB is converted to sRGB
  (LittleCMS via Pillow's ImageCms, relative colorimetric), because every LDR value the
  engine reads is taken as sRGB-encoded; out-of-gamut colours clip. An sRGB profile is left
  alone. A profile LittleCMS cannot parse is reported and ignored.
* **Exposure** (`ExposureTime` 0x829A seconds, `PhotographicSensitivity` 0x8827 ISO,
  `FNumber` 0x829D): a photo's exposure in stops is log2(time × ISO / N²), higher = brighter
  (`ImageMetadata.exposure_stops`; without `FNumber` the aperture is taken as fixed, as on
  phones). A set of photos whose every one states time and ISO gets per-frame exposures
  relative to its first (`frames_exposure_ev`); one that does not, none.
* **Video rotation**: the display matrix's rotation (PyAV `VideoFrame.rotation`, counter-
  clockwise degrees, or an old `rotate` stream tag, clockwise) is applied to every frame in
  multiples of 90 degrees. Flips in the display matrix are not applied (reported).
"""
from __future__ import annotations

import io
import math
from dataclasses import asdict, dataclass

import numpy as np
from PIL import ExifTags, Image, ImageCms

from core.camera import Intrinsics

FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # 43.27 mm
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # FocalPlaneResolutionUnit -> mm per unit

# EXIF orientation -> Pillow transpose (the table ImageOps.exif_transpose uses)
_TRANSPOSE = {
    2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180, 4: Image.Transpose.FLIP_TOP_BOTTOM,
    5: Image.Transpose.TRANSPOSE, 6: Image.Transpose.ROTATE_270, 7: Image.Transpose.TRANSVERSE,
    8: Image.Transpose.ROTATE_90,
}
_ORIENTATION_NAMES = {1: "upright", 2: "mirrored", 3: "rotated 180", 4: "flipped vertically",
                      5: "transposed", 6: "rotated 90 cw to view", 7: "transversed", 8: "rotated 90 ccw to view"}


@dataclass(frozen=True)
class ImageMetadata:
    orientation: int = 1
    focal_length_mm: float | None = None
    focal_length_35mm: float | None = None
    focal_plane_px_per_mm: float | None = None
    exif_width: int | None = None
    make: str | None = None
    model: str | None = None
    icc_description: str | None = None
    icc_is_srgb: bool | None = None
    icc_error: str | None = None
    exposure_time_s: float | None = None
    iso: float | None = None
    f_number: float | None = None

    def as_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}

    def exposure_stops(self, with_aperture: bool = True) -> float | None:
        """log2(time x ISO / N^2) (without the aperture when `with_aperture` is false); None
        unless the file states time and ISO."""
        if self.exposure_time_s is None or self.iso is None or (with_aperture and self.f_number is None):
            return None
        stops = math.log2(self.exposure_time_s * self.iso)
        return stops - 2.0 * math.log2(self.f_number) if with_aperture else stops


MAX_EXIF_EXPOSURE_SPREAD_STOPS = 20.0  # CaptureParams' bound on frame_ev: a wider spread is a broken file


def frames_exposure_ev(metas: list[ImageMetadata]) -> list[float] | None:
    """Each photo's exposure in stops relative to the first, when every photo states its
    exposure time and ISO (the aperture too if any does), else None; also None for one
    photo, or for a spread past MAX_EXIF_EXPOSURE_SPREAD_STOPS."""
    if len(metas) < 2:
        return None
    aperture = any(m.f_number is not None for m in metas)
    stops = [m.exposure_stops(with_aperture=aperture) for m in metas]
    if any(s is None for s in stops):
        return None
    ev = [s - stops[0] for s in stops]
    return ev if max(abs(e) for e in ev) <= MAX_EXIF_EXPOSURE_SPREAD_STOPS else None


def _number(v) -> float | None:
    try:
        x = float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) and x > 0 else None


def _text(v) -> str | None:
    if isinstance(v, bytes):
        v = v.decode("ascii", "replace")
    return v.strip("\x00 ").strip() or None if isinstance(v, str) else None


def _icc(image: Image.Image) -> tuple[str | None, bool | None, str | None]:
    data = image.info.get("icc_profile")
    if not data:
        return None, None, None
    try:
        profile = ImageCms.ImageCmsProfile(io.BytesIO(data))
        desc = (ImageCms.getProfileDescription(profile) or "").strip()
    except (OSError, ImageCms.PyCMSError, ValueError) as exc:
        return None, None, f"unreadable ICC profile ignored ({exc})"
    return desc or "unnamed profile", "srgb" in desc.lower().replace(" ", ""), None


def image_metadata(image: Image.Image) -> ImageMetadata:
    """Metadata of an opened (not necessarily decoded) Pillow image."""
    try:
        exif = image.getexif()
        sub = exif.get_ifd(ExifTags.IFD.Exif)
    except Exception:  # a malformed EXIF block is not a reason to refuse the pixels
        exif, sub = {}, {}
    orientation = exif.get(ExifTags.Base.Orientation, 1)
    orientation = orientation if isinstance(orientation, int) and 1 <= orientation <= 8 else 1
    px_per_mm = None
    xres, unit = (
        _number(sub.get(ExifTags.Base.FocalPlaneXResolution)),
        sub.get(ExifTags.Base.FocalPlaneResolutionUnit, 2),
    )
    if xres is not None and unit in _UNIT_MM:
        px_per_mm = xres / _UNIT_MM[unit]
    exif_width = sub.get(ExifTags.Base.ExifImageWidth)
    desc, is_srgb, icc_error = _icc(image)
    return ImageMetadata(
        orientation=orientation,
        focal_length_mm=_number(sub.get(ExifTags.Base.FocalLength)),
        focal_length_35mm=_number(sub.get(ExifTags.Base.FocalLengthIn35mmFilm)),
        focal_plane_px_per_mm=px_per_mm,
        exif_width=int(exif_width) if isinstance(exif_width, int) and exif_width > 0 else None,
        make=_text(exif.get(ExifTags.Base.Make)), model=_text(exif.get(ExifTags.Base.Model)),
        icc_description=desc, icc_is_srgb=is_srgb, icc_error=icc_error,
        exposure_time_s=_number(sub.get(ExifTags.Base.ExposureTime)),
        iso=_number(_first(sub.get(ExifTags.Base.ISOSpeedRatings))),
        f_number=_number(sub.get(ExifTags.Base.FNumber)),
    )


def _first(v):
    """ISO may be stored as a tuple of values (EXIF allows several): the first."""
    return v[0] if isinstance(v, (tuple, list)) and v else v


def orient_image(image: Image.Image, orientation: int) -> Image.Image:
    t = _TRANSPOSE.get(orientation)
    return image if t is None else image.transpose(t)


def orient_array(a: np.ndarray, orientation: int) -> np.ndarray:
    """The same transposes on an [H, W, ...] array (for pixels Pillow did not decode)."""
    ops = {
        2: lambda x: x[:, ::-1], 3: lambda x: x[::-1, ::-1], 4: lambda x: x[::-1],
        5: lambda x: np.swapaxes(x, 0, 1), 6: lambda x: np.rot90(x, -1), 7: lambda x: np.rot90(x, 2).swapaxes(0, 1),
        8: lambda x: np.rot90(x, 1),
    }
    op = ops.get(orientation)
    return a if op is None else np.ascontiguousarray(op(a))


def orientation_swaps_axes(orientation: int) -> bool:
    return orientation in (5, 6, 7, 8)


def describe_orientation(orientation: int) -> str:
    return f"EXIF orientation {orientation} ({_ORIENTATION_NAMES.get(orientation, 'unknown')})"


def exif_intrinsics(meta: ImageMetadata, width: int, height: int, stored_width: int | None = None
                    ) -> tuple[Intrinsics, str] | None:
    """Intrinsics of the UPRIGHT image (width x height) from EXIF, with the rule used; None if the
    file does not fix them. `stored_width` is the width as stored (before orientation)."""
    if meta.focal_length_35mm is not None:
        f = meta.focal_length_35mm * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM
        rule = f"EXIF FocalLengthIn35mmFilm = {meta.focal_length_35mm:g} mm (diagonal crop factor)"
    elif meta.focal_length_mm is not None and meta.focal_plane_px_per_mm is not None:
        stored = (
            stored_width
            if stored_width is not None
            else (height if orientation_swaps_axes(meta.orientation) else width)
        )
        ratio = stored / meta.exif_width if meta.exif_width else 1.0
        f = meta.focal_length_mm * meta.focal_plane_px_per_mm * ratio
        rule = (f"EXIF FocalLength = {meta.focal_length_mm:g} mm x FocalPlaneXResolution "
                f"{meta.focal_plane_px_per_mm:g} px/mm" + (f" x {ratio:.4g} (resized)" if ratio != 1.0 else ""))
    else:
        return None
    if not (math.isfinite(f) and f > 0):
        return None
    k = Intrinsics(f, f, width / 2.0, height / 2.0, width, height)
    if not (1.0 < k.hfov_deg < 179.0):
        return None
    return k, rule


def to_srgb(image: Image.Image, meta: ImageMetadata) -> tuple[Image.Image, str | None]:
    """(RGB image in sRGB, what was done or None). Converts only a readable non-sRGB profile."""
    if meta.icc_description is None or meta.icc_is_srgb:
        return image, None
    try:
        src = ImageCms.ImageCmsProfile(io.BytesIO(image.info["icc_profile"]))
        out = ImageCms.profileToProfile(image.convert("RGB"), src, ImageCms.createProfile("sRGB"),
                                        renderingIntent=ImageCms.Intent.RELATIVE_COLORIMETRIC, outputMode="RGB")
    except (OSError, ImageCms.PyCMSError, ValueError, KeyError) as exc:
        return image, f"colour profile {meta.icc_description!r} could not be converted ({exc}); pixels used as sRGB"
    return out, f"converted from ICC profile {meta.icc_description!r} to sRGB (relative colorimetric)"


# ---------------------------------------------------------------------------------------
# Video
# ---------------------------------------------------------------------------------------
def video_rotation_ccw(stream, first_frame) -> int:
    """Counter-clockwise display rotation in degrees (multiple of 90, in [0, 360)) of a PyAV
    stream: the frame's display matrix, else the legacy `rotate` tag (clockwise degrees)."""
    deg = getattr(first_frame, "rotation", 0) or 0
    if not deg:
        tag = (getattr(stream, "metadata", None) or {}).get("rotate")
        try:
            deg = -int(float(tag)) if tag is not None else 0
        except ValueError:
            deg = 0
    return int(round(deg / 90.0)) * 90 % 360


def rotate_frames(frames: np.ndarray, ccw_degrees: int) -> np.ndarray:
    """[T, H, W, C] frames rotated counter-clockwise by a multiple of 90 degrees."""
    k = (ccw_degrees // 90) % 4
    return frames if k == 0 else np.ascontiguousarray(np.rot90(frames, k, axes=(1, 2)))
