"""Media I/O with limits: every user-triggerable failure raises `MediaError` (a
ValueError) with a stable `.code`; see core.io.limits.HTTP_STATUS for the code list."""
from core.io.colour import StatedTransfer
from core.io.depth import encode_depth_png16, probe_depth, read_depth, sanitize_depth, write_depth_npz
from core.io.envmap_io import MEDIA_TYPES, encode_envmap, load_envmap, save_envmap, tonemapped_preview
from core.io.exr import HalfOverflowWarning, encode_exr, read_exr, read_exr_channels, write_exr
from core.io.hdr import encode_hdr, read_hdr, write_hdr
from core.io.images import encode_png, encode_png16, probe_image, read_image, read_png16, write_png, write_png16
from core.io.limits import DEFAULT_LIMITS, ERROR_CODES, HTTP_STATUS, MediaError, MediaLimits
from core.io.sniff import sniff_depth, sniff_hdr_image, sniff_media
from core.io.video import VideoFrames, VideoHeader, probe_video, read_video, select_frame_indices, write_video

__all__ = [
    "DEFAULT_LIMITS",
    "ERROR_CODES",
    "HTTP_STATUS",
    "HalfOverflowWarning",
    "MEDIA_TYPES",
    "MediaError",
    "MediaLimits",
    "StatedTransfer",
    "VideoFrames",
    "VideoHeader",
    "encode_depth_png16",
    "encode_envmap",
    "encode_exr",
    "encode_hdr",
    "encode_png",
    "encode_png16",
    "load_envmap",
    "read_depth",
    "read_exr",
    "read_exr_channels",
    "read_hdr",
    "probe_depth",
    "probe_image",
    "probe_video",
    "read_image",
    "read_png16",
    "read_video",
    "sanitize_depth",
    "save_envmap",
    "select_frame_indices",
    "sniff_depth",
    "sniff_hdr_image",
    "sniff_media",
    "tonemapped_preview",
    "write_depth_npz",
    "write_exr",
    "write_hdr",
    "write_png",
    "write_png16",
    "write_video",
]
