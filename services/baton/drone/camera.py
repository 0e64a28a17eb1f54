"""The drone's camera: a local image source behind the Camera service.

Two sources: a static image file (its bytes, as they are), or a generated
picture, a binary PPM (``P6``) of width*height*3 bytes plus its header, about
1 MB at the default 640x546. The generated pixels are computed once per
resolution (numpy) and each picture stamps its sequence number into a
copy, so no two pictures are equal and a replayed reply can be told apart
from a fresh one.

Every picture produced is counted where it is produced, one line in the
camera's effects file (``baton.effects``, ``baton drone --camera-effects-file``),
for the testbed's exactly-once check that does not trust the drone's audit,
with the position where it was taken. The pictures themselves are not kept:
with ``thumbnails_dir`` (``baton drone --thumbnails-dir``) the camera keeps a
small JPEG of each (at most ``THUMBNAIL_SIDE`` pixels a side, about 3 KB, the
first ``MAX_THUMBNAILS`` of a run), ``picture-SEQ.jpg`` by the picture's effects
sequence number, for the testbed's HTML report.
"""

from __future__ import annotations

import asyncio
import io
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
# Thumbnails kept (thumbnails_dir): their longer side, in pixels, and how many a run
# keeps at most (about 3 KB each: 1.5 MB in all).
THUMBNAIL_SIDE = 96
MAX_THUMBNAILS = 500

PositionSource = Callable[[], Awaitable[api.Position]]
# Where the gimbal points now: the vehicle's region of interest, None when none is set.
AimSource = Callable[[], api.Position | None]


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


def thumbnail_jpeg(image: bytes, side: int = THUMBNAIL_SIDE) -> bytes | None:
    """A JPEG of ``image`` (PPM, PNG, JPEG: what Pillow reads) at most ``side`` pixels a
    side; None for bytes that are no image Pillow knows."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(image)) as picture:
            picture.thumbnail((side, side))
            out = io.BytesIO()
            picture.convert("RGB").save(out, "JPEG", quality=80)
    except (OSError, ValueError, UnidentifiedImageError):
        return None
    return out.getvalue()


def thumbnail_name(seq: int) -> str:
    """The file of picture ``seq``'s thumbnail (its effects sequence number) in the folder."""
    return f"picture-{seq}.jpg"


THUMBNAIL_GLOB = "picture-*.jpg"


class Camera:
    """The Camera service's two RPCs over a static file or a generated picture.

    ``effects_file``: where each picture produced is counted (seq, time,
    resolution, bytes, where it was taken); None counts in memory only
    (``effects.seq``). ``thumbnails_dir``: where to keep each picture's thumbnail
    (``thumbnail_name``); None keeps none. ``aim``: where the gimbal points (the
    vehicle backend's ``looking_at``), recorded with each picture as where it looked.
    """

    def __init__(
        self,
        position: PositionSource,
        image_file: str | Path | None = None,
        resolution: tuple[int, int] = DEFAULT_RESOLUTION,
        effects_file: str | Path | None = None,
        thumbnails_dir: str | Path | None = None,
        aim: AimSource | None = None,
    ) -> None:
        check_resolution(*resolution)
        self._aim = aim
        self.thumbnails_dir = Path(thumbnails_dir) if thumbnails_dir is not None else None
        self.thumbnails = 0  # kept by this process (MAX_THUMBNAILS at most)
        if self.thumbnails_dir is not None:
            try:
                self.thumbnails_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise OSError(
                    f"thumbnails folder {self.thumbnails_dir} (--thumbnails-dir): "
                    f"{exc.strerror or exc}; give a writable folder"
                ) from exc
            # A restarted drone continues the run's count.
            self.thumbnails = sum(1 for _ in self.thumbnails_dir.glob(THUMBNAIL_GLOB))
        self._position = position
        self.effects = EffectsFile(effects_file, "--camera-effects-file")
        # The picture number, as a camera numbers its pictures: a drone restarted on
        # the same effects file (every line of it a picture) goes on from its count,
        # so no two pictures of a run carry one number.
        self.sequence = self.effects.seq
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

    def picture(
        self, where: api.Position | None = None, looking_at: api.Position | None = None
    ) -> tuple[bytes, int]:
        """The next picture's bytes and its effects sequence number, counted in the effects
        file (with ``where`` it was taken, if known, and the region of interest it
        ``looking_at``, if one was set); advances the sequence number."""
        image = self._produce()
        width, height = self.resolution
        place: dict[str, float] = {}
        if where is not None and (where.latitude_deg or where.longitude_deg):
            place = {"latitude_deg": where.latitude_deg, "longitude_deg": where.longitude_deg}
        if looking_at is not None:
            place["looking_at_latitude_deg"] = looking_at.latitude_deg
            place["looking_at_longitude_deg"] = looking_at.longitude_deg
        seq = self.effects.record(
            "picture", resolution=f"{width}x{height}", bytes=len(image), **place
        )
        return image, seq

    async def _keep_thumbnail(self, image: bytes, seq: int) -> None:
        """Writes picture ``seq``'s thumbnail, while fewer than MAX_THUMBNAILS are kept."""
        if self.thumbnails_dir is None or self.thumbnails >= MAX_THUMBNAILS:
            return
        self.thumbnails += 1
        folder = self.thumbnails_dir

        def write() -> None:
            small = thumbnail_jpeg(image)
            if small is not None:
                (folder / thumbnail_name(seq)).write_bytes(small)

        await asyncio.to_thread(write)

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
        """A picture with the vehicle's position, where the gimbal pointed (if at a region
        of interest) and its sequence number. UNAVAILABLE, nothing taken, while the
        vehicle's position is not known (the source's all-zero Position): a picture is
        the mission's at a place, and one of no known place cannot be told to be the
        waypoint's (the caller sends it again)."""
        position = await self._position()
        if not (position.latitude_deg or position.longitude_deg):
            raise StatusError(
                grpc.StatusCode.UNAVAILABLE,
                "Camera.TakePicture: the vehicle's position is not known now; no picture was taken",
            )
        looking_at = self._aim() if self._aim is not None else None
        image, seq = self.picture(position, looking_at)
        width, height = self.resolution
        sequence = self.sequence
        await self._keep_thumbnail(image, seq)
        return api.TakePictureReply(
            image=image,
            format=self.format,
            width=width,
            height=height,
            position=position,
            sequence=sequence,
            looking_at=looking_at,
        )
