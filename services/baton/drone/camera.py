"""The drone's camera: a local image source behind the Camera service.

Two sources: a static image file (its bytes, as they are), or a generated
picture, a binary PPM (``P6``) of width*height*3 bytes plus its header, about
1 MB at the default 640x546. The generated pixels are computed once per
resolution (numpy) and each picture stamps its sequence number into a
copy, so no two pictures are equal and a replayed reply can be told apart
from a fresh one.

Every picture produced is counted where it is produced, one line in the
camera's effects file (``baton.effects``, ``baton drone --camera-effects-file``),
for the testbed's exactly-once check that does not trust the drone's audit.
"""

from __future__ import annotations

import struct
from collections.abc import Awaitable, Callable
from pathlib import Path

import grpc
import numpy as np

from baton.effects import EffectsFile
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api

DEFAULT_RESOLUTION = (640, 546)  # 1,048,320 pixel bytes: the paper's ~1 MB picture
MIN_SIDE = 16
MAX_SIDE = 8192
# Rows of the picture that carry the sequence stamp.
_STAMP_ROWS = 8

PositionSource = Callable[[], Awaitable[api.Position]]


def parse_resolution(text: str) -> tuple[int, int]:
    """``(width, height)`` from ``WxH``; ValueError saying what is wrong otherwise."""
    width, sep, height = text.lower().partition("x")
    if not sep or not width.strip().isdigit() or not height.strip().isdigit():
        raise ValueError(f"expected a resolution like '640x546', got {text!r}")
    resolution = int(width), int(height)
    check_resolution(*resolution)
    return resolution


def check_resolution(width: int, height: int) -> None:
    """ValueError unless both sides are in [MIN_SIDE, MAX_SIDE]."""
    for side, value in (("width", width), ("height", height)):
        if not MIN_SIDE <= value <= MAX_SIDE:
            raise ValueError(f"{side} {value} is out of range; use {MIN_SIDE}..{MAX_SIDE} pixels")


def ppm_header(width: int, height: int) -> bytes:
    """The header of a binary 8-bit PPM."""
    return b"P6\n%d %d\n255\n" % (width, height)


def generate_pixels(width: int, height: int) -> np.ndarray:
    """A deterministic test picture (gradients and a grid), height x width x 3 bytes."""
    x = np.arange(width, dtype=np.uint32)[None, :]
    y = np.arange(height, dtype=np.uint32)[:, None]
    image = np.empty((height, width, 3), dtype=np.uint8)
    image[..., 0] = (x * 255 // max(width - 1, 1)).astype(np.uint8)
    image[..., 1] = (y * 255 // max(height - 1, 1)).astype(np.uint8)
    image[..., 2] = ((x // 32 + y // 32) % 2 * 160 + (x ^ y) % 64).astype(np.uint8)
    return image


def image_size(data: bytes) -> tuple[int, int]:
    """Width and height of a PPM or PNG image; (0, 0) for other formats."""
    if data[:2] == b"P6":
        fields = data.split(maxsplit=3)
        if len(fields) >= 3 and fields[1].isdigit() and fields[2].isdigit():
            return int(fields[1]), int(fields[2])
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        width, height = struct.unpack(">II", data[16:24])
        return width, height
    return 0, 0


class Camera:
    """The Camera service's two RPCs over a static file or a generated picture.

    ``effects_file``: where each picture produced is counted (seq, time,
    resolution, bytes); None counts in memory only (``effects.seq``).
    """

    def __init__(
        self,
        position: PositionSource,
        image_file: str | Path | None = None,
        resolution: tuple[int, int] = DEFAULT_RESOLUTION,
        effects_file: str | Path | None = None,
    ) -> None:
        check_resolution(*resolution)
        self._position = position
        self.effects = EffectsFile(effects_file, "--camera-effects-file")
        self.sequence = 0
        self.resolution = resolution
        self._static: bytes | None = None
        self.format = "ppm"
        if image_file is not None:
            path = Path(image_file)
            try:
                self._static = path.read_bytes()
            except OSError as exc:
                raise ValueError(f"{path}: cannot read the camera image: {exc.strerror}") from None
            self.format = path.suffix.lstrip(".").lower() or "bin"
            self.resolution = image_size(self._static)
        # Only the current resolution's pixels are kept: 8192x8192 is 192 MiB.
        self._cached: tuple[tuple[int, int], bytes] | None = None

    def _pixels(self) -> bytes:
        if self._cached is None or self._cached[0] != self.resolution:
            width, height = self.resolution
            self._cached = (
                self.resolution,
                ppm_header(width, height) + generate_pixels(width, height).tobytes(),
            )
        return self._cached[1]

    def picture(self) -> bytes:
        """The next picture's bytes, counted in the effects file; advances the sequence number."""
        image = self._produce()
        width, height = self.resolution
        self.effects.record("picture", resolution=f"{width}x{height}", bytes=len(image))
        return image

    def _produce(self) -> bytes:
        self.sequence += 1
        if self._static is not None:
            return self._static
        base = self._pixels()
        width, height = self.resolution
        picture = bytearray(base)
        # Stamp the sequence number over the first rows, so pictures differ.
        header = len(base) - width * height * 3
        stamp = struct.pack(">Q", self.sequence)
        rows = min(_STAMP_ROWS, height) * width * 3
        picture[header : header + rows] = (stamp * (rows // 8 + 1))[:rows]
        return bytes(picture)

    async def SetResolution(self, request: api.SetResolutionRequest) -> api.SetResolutionReply:
        """Sets the resolution of later generated pictures (a static file keeps its own)."""
        try:
            check_resolution(request.width, request.height)
        except ValueError as exc:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"SetResolution: {exc}") from None
        if self._static is None:
            self.resolution = (request.width, request.height)
        width, height = self.resolution
        return api.SetResolutionReply(width=width, height=height)

    async def TakePicture(self, request: api.TakePictureRequest) -> api.TakePictureReply:
        """A picture with the vehicle's position and its sequence number."""
        image = self.picture()
        width, height = self.resolution
        return api.TakePictureReply(
            image=image,
            format=self.format,
            width=width,
            height=height,
            position=await self._position(),
            sequence=self.sequence,
        )
