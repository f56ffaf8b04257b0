"""Streaming `multipart/form-data` reader for POST /jobs.

Starlette's form parser spools every file to a temporary file with no size bound before a
handler runs. Here the body is parsed chunk by chunk as it arrives: file parts go straight
to the job's upload directory and the request is refused (413) the moment a part exceeds
its limit, so neither memory nor disk use ever exceeds the configured bounds.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import AsyncIterator, BinaryIO

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header

from service.config import ServiceLimits
from service.errors import BadRequest, InvalidInput, PayloadTooLarge, UnsupportedMedia

FILE_PARTS = ("file", "depth")
TEXT_PARTS = ("params",)
MULTIPART_OVERHEAD = 64 * 1024  # headers and boundaries on top of the parts' own limits


@dataclass
class PartState:
    name: str
    size: int = 0
    sink: BinaryIO | None = None
    text: bytearray = field(default_factory=bytearray)


@dataclass
class ReceivedForm:
    """What arrived: file parts saved as `<name>.upload` in the destination directory."""

    files: dict[str, Path] = field(default_factory=dict)
    sizes: dict[str, int] = field(default_factory=dict)
    texts: dict[str, str] = field(default_factory=dict)


class FormReader:
    def __init__(self, dest: Path, limits: ServiceLimits):
        self.dest = dest
        self.part_limits = {"file": limits.max_upload_bytes, "depth": limits.max_depth_bytes,
                            "params": limits.max_params_bytes}
        self.form = ReceivedForm()
        self._headers: dict[bytes, bytes] = {}
        self._hfield = bytearray()
        self._hvalue = bytearray()
        self._part: PartState | None = None
        self._ended = False

    @property
    def max_body_bytes(self) -> int:
        return sum(self.part_limits.values()) + MULTIPART_OVERHEAD

    # -- parser callbacks ------------------------------------------------------------------
    def _on_part_begin(self) -> None:
        self._headers = {}

    def _on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._hfield += data[start:end]

    def _on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._hvalue += data[start:end]

    def _on_header_end(self) -> None:
        self._headers[bytes(self._hfield).lower()] = bytes(self._hvalue)
        self._hfield.clear()
        self._hvalue.clear()

    def _on_headers_finished(self) -> None:
        _, options = parse_options_header(self._headers.get(b"content-disposition", b""))
        name = options.get(b"name", b"").decode("utf-8", "replace")
        if name not in FILE_PARTS + TEXT_PARTS:
            raise InvalidInput(f"unknown form field {name!r}; expected file, depth, params", code="unknown_field")
        if name in self.form.sizes:
            raise InvalidInput(f"form field {name!r} was sent twice", code="duplicate_field")
        part = PartState(name)
        if name in FILE_PARTS:
            path = self.dest / f"{name}.upload"
            part.sink = open(path, "wb")
            self.form.files[name] = path
        self.form.sizes[name] = 0
        self._part = part

    def _on_part_data(self, data: bytes, start: int, end: int) -> None:
        part = self._part
        part.size += end - start
        if part.size > self.part_limits[part.name]:
            raise PayloadTooLarge(f"form field {part.name!r} exceeds its limit of "
                                  f"{self.part_limits[part.name]} bytes", code="too_large")
        if part.sink is not None:
            part.sink.write(data[start:end])
        else:
            part.text += data[start:end]

    def _on_part_end(self) -> None:
        part, self._part = self._part, None
        if part is None:
            return
        self.form.sizes[part.name] = part.size
        if part.sink is not None:
            part.sink.close()
        else:
            try:
                self.form.texts[part.name] = part.text.decode("utf-8")
            except UnicodeDecodeError:
                raise InvalidInput(f"form field {part.name!r} is not UTF-8 text", code="invalid_params") from None

    def _on_end(self) -> None:
        self._ended = True

    def close(self) -> None:
        if self._part is not None and self._part.sink is not None:
            self._part.sink.close()

    async def read(self, content_type: str | None, content_length: str | None,
                   chunks: AsyncIterator[bytes]) -> ReceivedForm:
        mime, options = parse_options_header(content_type or "")
        if mime != b"multipart/form-data" or not options.get(b"boundary"):
            raise UnsupportedMedia("POST /jobs takes multipart/form-data (fields file, depth, params)",
                                   code="not_multipart")
        if content_length and content_length.isdigit() and int(content_length) > self.max_body_bytes:
            raise PayloadTooLarge(f"request body of {content_length} bytes exceeds the limit of "
                                  f"{self.max_body_bytes} bytes", code="too_large")
        parser = MultipartParser(options[b"boundary"], callbacks={
            "on_part_begin": self._on_part_begin, "on_part_data": self._on_part_data,
            "on_part_end": self._on_part_end, "on_header_field": self._on_header_field,
            "on_header_value": self._on_header_value, "on_header_end": self._on_header_end,
            "on_headers_finished": self._on_headers_finished, "on_end": self._on_end,
        })
        try:
            await feed_multipart(parser, chunks)
        finally:
            self.close()
        if not self._ended:
            raise BadRequest("multipart body ended before its closing boundary (truncated upload?)",
                             code="truncated_body")
        if "file" not in self.form.files:
            raise InvalidInput("form field 'file' (the image or video) is required", code="missing_file")
        return self.form


async def feed_multipart(parser, chunks: AsyncIterator[bytes]) -> None:
    """Stream `chunks` through a python-multipart parser; a malformed body is a 400 naming why."""
    try:
        async for chunk in chunks:
            if chunk:
                parser.write(chunk)
        parser.finalize()
    except FormParserError as exc:
        raise BadRequest(f"malformed multipart body: {exc}", code="malformed_body") from None
