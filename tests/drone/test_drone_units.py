"""Unit tests of the drone's pieces: reply cache, handover script, dispatch, camera."""

from __future__ import annotations

import io
from pathlib import Path

import grpc
import pytest
from drone_fakes import FakeMobility

from baton.certs.make import ensure
from baton.digest import request_digest
from baton.drone import camera as camera_module
from baton.drone.camera import (
    THUMBNAIL_SIDE,
    Camera,
    image_size,
    parse_resolution,
    thumbnail_jpeg,
    thumbnail_name,
)
from baton.drone.dedupe import CachedReply, ReplyCache, retained_batches
from baton.drone.dispatch import Dispatcher
from baton.drone.master import HandoverScriptError, load_handover_script, parse_handover_script
from baton.drone.mobility import MavsdkMobility
from baton.drone.safety import VehicleLimits, fence_params
from baton.effects import read_effects
from baton.rpc.errors import StatusError
from baton.rpc.methods import drone_api
from baton.rpc.tls import DRONE, TlsError
from baton.sdk.fence import Fence, FencePolygon
from baton.v1 import drone_api_pb2 as api

ALL_METHODS = sorted(drone_api())


def test_reply_cache_keeps_the_last_window_only_below_the_watermark() -> None:
    cache = ReplyCache(window=3)
    cache.raise_watermark(10)
    for reqnr in range(1, 11):
        cache.store(reqnr, "/m", request_digest("/m", b"%d" % reqnr), b"r%d" % reqnr)
    assert cache.reqnrs == [8, 9, 10]
    assert cache.retained == (0, 0)
    assert cache.get(7) is None
    hit = cache.get(9)
    assert hit is not None and hit.reply == b"r9" and hit.digest == request_digest("/m", b"9")


def test_reply_cache_retains_every_reply_above_the_watermark() -> None:
    cache = ReplyCache(window=3)
    for reqnr in range(1, 11):
        cache.store(reqnr, "/m", request_digest("/m", b"%d" % reqnr), b"r%d" % reqnr)
    assert cache.reqnrs == list(range(1, 11))  # nobody is known to hold any of them
    cache.raise_watermark(6)
    assert cache.reqnrs == [7, 8, 9, 10]  # above it, though beyond the window
    assert cache.retained == (4, 9)  # b"r7" .. b"r10"
    cache.raise_watermark(2)  # it never goes down
    assert cache.watermark == 6
    cache.raise_watermark(9)
    assert cache.reqnrs == [8, 9, 10]


def test_retained_replies_go_in_batches_of_a_bounded_size_in_order() -> None:
    """A taker answers its program from the first batch while the next crosses the link;
    a reply larger than a batch goes alone, and nothing is lost or reordered."""
    sizes = [10, 20, 30, 100, 5, 5, 60]
    replies = [CachedReply(n + 1, "/m", b"", b"x" * size) for n, size in enumerate(sizes)]
    batches = retained_batches(replies, max_bytes=60)
    assert [[r.reqnr for r in batch] for batch in batches] == [[1, 2, 3], [4], [5, 6], [7]]
    assert [r for batch in batches for r in batch] == replies
    assert retained_batches([], max_bytes=60) == []


def test_reply_cache_rejects_an_empty_window() -> None:
    with pytest.raises(ValueError, match="window"):
        ReplyCache(window=0)


def test_request_digest_separates_method_and_payload() -> None:
    assert request_digest("/a", b"bc") != request_digest("/ab", b"c")


def test_handover_script_parses_comments_and_blank_lines() -> None:
    script = parse_handover_script("# header\n\n5 1  # to one\n 9 2\n", "h.txt", [0, 1, 2])
    assert {k: (v.new_master, v.line) for k, v in script.items()} == {5: (1, 3), 9: (2, 4)}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("5 1\nfive 1\n", r"h\.txt:2: expected 'REQNR CONTROLLER_ID'"),
        ("5\n", r"h\.txt:1: expected"),
        ("5 1 2\n", r"h\.txt:1: expected"),
        ("\n\n5 7\n", r"h\.txt:3: unknown controller id 7; known ids: \[0, 1, 2\]"),
        ("0 1\n", r"h\.txt:1: request numbers start at 1"),
        ("5 1\n5 2\n", r"h\.txt:2: reqnr 5 already has a handover \(line 1\)"),
        ("-3 1\n", r"h\.txt:1: expected"),
    ],
)
def test_handover_script_errors_name_file_and_line(text: str, message: str) -> None:
    with pytest.raises(HandoverScriptError, match=message):
        parse_handover_script(text, "h.txt", [0, 1, 2])


def test_handover_script_missing_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(HandoverScriptError, match="cannot read"):
        load_handover_script(tmp_path / "nope", [0])


def test_routes_cover_every_drone_api_method() -> None:
    services = {name.split("/")[1] for name in ALL_METHODS}
    assert services == {
        "baton.v1.Mobility",
        "baton.v1.Camera",
        "baton.v1.Gimbal",
        "baton.v1.Clock",
    }
    assert "/baton.v1.Mobility/GetPosition" in ALL_METHODS


@pytest.mark.parametrize("method", ALL_METHODS)
async def test_dispatch_of_every_method(method: str) -> None:
    camera = Camera(_zero_position, resolution=(16, 16))
    dispatcher = Dispatcher({"Mobility": FakeMobility(), "Camera": camera})
    route = dispatcher.routes[method]
    if route.service == "Clock":
        with pytest.raises(StatusError) as info:
            dispatcher.route(method)
        assert info.value.code == grpc.StatusCode.UNIMPLEMENTED
        assert "Clock is answered by the controller" in info.value.message
        return
    assert dispatcher.route(method) is route
    request = route.request_type()
    if method.endswith("/SetResolution"):
        request = api.SetResolutionRequest(width=32, height=16)
    elif method.endswith("/Takeoff"):
        await dispatcher.handler(dispatcher.route("/baton.v1.Mobility/Arm"))(api.ArmRequest())
    parsed = route.parse(request.SerializeToString())
    reply = await dispatcher.handler(route)(parsed)
    assert isinstance(reply, route.reply_type)


async def test_the_gimbal_is_answered_by_the_vehicle_backend_and_aims_the_camera() -> None:
    vehicle = FakeMobility()
    camera = Camera(_zero_position, resolution=(16, 16), aim=vehicle.looking_at)
    dispatcher = Dispatcher({"Mobility": vehicle, "Camera": camera})
    set_roi = dispatcher.handler(dispatcher.route("/baton.v1.Gimbal/SetRoiLocation"))
    await set_roi(api.SetRoiLocationRequest(latitude_deg=47.1, longitude_deg=8.2))
    picture = await camera.TakePicture(api.TakePictureRequest())
    assert picture.HasField("looking_at") and picture.looking_at.latitude_deg == 47.1
    assert camera.effects.seq == 1
    await dispatcher.handler(dispatcher.route("/baton.v1.Gimbal/ClearRoi"))(api.ClearRoiRequest())
    assert not (await camera.TakePicture(api.TakePictureRequest())).HasField("looking_at")
    assert vehicle.calls == ["SetRoiLocation", "ClearRoi"]


def test_dispatch_unknown_method_and_bad_payload() -> None:
    dispatcher = Dispatcher({})
    with pytest.raises(StatusError) as info:
        dispatcher.route("/baton.v1.Mobility/Fly")
    assert info.value.code == grpc.StatusCode.UNIMPLEMENTED
    route = dispatcher.route("/baton.v1.Mobility/Takeoff")
    with pytest.raises(StatusError) as info:
        route.parse(b"\xff\xff\xff")
    assert info.value.code == grpc.StatusCode.INVALID_ARGUMENT


async def _zero_position() -> api.Position:
    return api.Position(latitude_deg=1.5)


async def test_a_restarted_camera_numbers_its_pictures_on_from_its_effects_file(
    tmp_path: Path,
) -> None:
    """Pictures 1 and 2, the drone killed, pictures 3 and 4 from a new process on the
    same effects file: no number twice (it restarted at 1 before)."""
    effects = tmp_path / "camera.jsonl"
    first = Camera(_zero_position, resolution=(16, 16), effects_file=effects)
    taken = [(await first.TakePicture(api.TakePictureRequest())).sequence for _ in range(2)]
    again = Camera(_zero_position, resolution=(16, 16), effects_file=effects)
    taken += [(await again.TakePicture(api.TakePictureRequest())).sequence for _ in range(2)]
    assert taken == [1, 2, 3, 4]


async def test_generated_picture_is_about_one_megabyte_and_varies() -> None:
    camera = Camera(_zero_position)
    first = await camera.TakePicture(api.TakePictureRequest())
    second = await camera.TakePicture(api.TakePictureRequest())
    header = b"P6\n640 546\n255\n"
    assert first.image.startswith(header)
    assert len(first.image) == len(header) + 640 * 546 * 3  # 1,048,320 pixel bytes
    assert (first.width, first.height, first.format) == (640, 546, "ppm")
    assert (first.sequence, second.sequence) == (1, 2)
    assert first.image != second.image
    assert first.position.latitude_deg == 1.5


@pytest.mark.parametrize(("width", "height"), [(16, 16), (17, 31), (1920, 1080)])
async def test_set_resolution_resizes_generated_pictures(width: int, height: int) -> None:
    camera = Camera(_zero_position)
    reply = await camera.SetResolution(api.SetResolutionRequest(width=width, height=height))
    assert (reply.width, reply.height) == (width, height)
    picture = await camera.TakePicture(api.TakePictureRequest())
    assert image_size(picture.image) == (width, height)
    assert len(picture.image) == len(b"P6\n%d %d\n255\n" % (width, height)) + width * height * 3


@pytest.mark.parametrize(("width", "height"), [(15, 100), (100, 8193), (0, 0)])
async def test_set_resolution_out_of_range(width: int, height: int) -> None:
    camera = Camera(_zero_position)
    with pytest.raises(StatusError) as info:
        await camera.SetResolution(api.SetResolutionRequest(width=width, height=height))
    assert info.value.code == grpc.StatusCode.INVALID_ARGUMENT


async def test_static_image_file(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "shot.ppm"
    path.write_bytes(b"P6\n20 10\n255\n" + bytes(600))
    camera = Camera(_zero_position, image_file=path)
    picture = await camera.TakePicture(api.TakePictureRequest())
    assert picture.image == path.read_bytes()
    assert (picture.format, picture.width, picture.height) == ("ppm", 20, 10)


async def test_the_camera_counts_every_picture_it_produced_in_its_effects_file(
    tmp_path,  # type: ignore[no-untyped-def]
) -> None:
    effects = tmp_path / "camera-effects.jsonl"
    camera = Camera(_zero_position, resolution=(16, 16), effects_file=effects)
    first = await camera.TakePicture(api.TakePictureRequest())
    await camera.SetResolution(api.SetResolutionRequest(width=32, height=20))
    second = await camera.TakePicture(api.TakePictureRequest())
    assert [
        (e["seq"], e["effect"], e["resolution"], e["bytes"]) for e in read_effects(effects)
    ] == [
        (1, "picture", "16x16", len(first.image)),
        (2, "picture", "32x20", len(second.image)),
    ]
    # A restarted drone's camera continues the count in the same file.
    restarted = Camera(_zero_position, resolution=(16, 16), effects_file=effects)
    await restarted.TakePicture(api.TakePictureRequest())
    assert [e["seq"] for e in read_effects(effects)] == [1, 2, 3]
    assert (camera.effects.seq, restarted.effects.seq) == (2, 3)


async def test_the_camera_keeps_a_small_thumbnail_of_each_picture_and_where_it_was_taken(
    tmp_path,  # type: ignore[no-untyped-def]
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from PIL import Image

    monkeypatch.setattr(camera_module, "MAX_THUMBNAILS", 3)
    effects, folder = tmp_path / "camera-effects.jsonl", tmp_path / "thumbnails"
    camera = Camera(_zero_position, effects_file=effects, thumbnails_dir=folder)
    for _ in range(2):
        await camera.TakePicture(api.TakePictureRequest())
    lines = read_effects(effects)
    assert [(e["seq"], e["latitude_deg"], e["longitude_deg"]) for e in lines] == [
        (1, 1.5, 0.0),
        (2, 1.5, 0.0),
    ]
    kept = sorted(folder.iterdir())
    assert [p.name for p in kept] == [thumbnail_name(1), thumbnail_name(2)]
    with Image.open(kept[0]) as small:
        assert small.format == "JPEG"
        assert small.size == (THUMBNAIL_SIDE, round(546 * THUMBNAIL_SIDE / 640))
    assert kept[0].stat().st_size < 10_000  # the 1 MB picture is not kept
    # A restarted drone continues the run's count; no more than MAX_THUMBNAILS a run.
    restarted = Camera(_zero_position, effects_file=effects, thumbnails_dir=folder)
    for _ in range(3):
        await restarted.TakePicture(api.TakePictureRequest())
    assert [e["seq"] for e in read_effects(effects)] == [1, 2, 3, 4, 5]
    assert sorted(p.name for p in folder.iterdir()) == sorted(thumbnail_name(k) for k in (1, 2, 3))


async def test_no_picture_is_taken_where_the_position_is_unknown(
    tmp_path,  # type: ignore[no-untyped-def]
) -> None:
    """The vehicle connected but its position not reported yet (no global position, a
    read that timed out): UNAVAILABLE, and the camera took and counted nothing."""

    async def unknown() -> api.Position:
        return api.Position()

    effects = tmp_path / "camera-effects.jsonl"
    camera = Camera(unknown, resolution=(16, 16), effects_file=effects)
    with pytest.raises(StatusError) as refused:
        await camera.TakePicture(api.TakePictureRequest())
    assert refused.value.code is grpc.StatusCode.UNAVAILABLE
    assert "position is not known now; no picture was taken" in refused.value.message
    assert read_effects(effects) == [] and camera.sequence == 0


def test_thumbnails_of_a_static_png_and_of_bytes_that_are_no_image(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from PIL import Image

    path = tmp_path / "shot.png"
    Image.new("RGB", (400, 100), (200, 30, 30)).save(path)
    small = thumbnail_jpeg(path.read_bytes())
    assert small is not None
    with Image.open(io.BytesIO(small)) as image:
        assert image.size == (THUMBNAIL_SIDE, 24)
    assert thumbnail_jpeg(b"not a picture") is None
    with pytest.raises(OSError, match="--thumbnails-dir"):
        Camera(_zero_position, thumbnails_dir=path / "under-a-file")


def test_parse_resolution() -> None:
    assert parse_resolution("640x546") == (640, 546)
    for bad in ("640", "axb", "8x8", "9000x100"):
        with pytest.raises(ValueError):
            parse_resolution(bad)


def _drone_args(*argv: str):  # type: ignore[no-untyped-def]
    from baton.cli import build_parser

    return build_parser().parse_args(["drone", *argv])


def test_cli_settings_from_flags_and_config(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from baton.drone.cli import settings_from_args

    ensure(tmp_path / "certs", [DRONE])  # the file's tls.certs, read from the file's folder
    config = tmp_path / "testbed.yaml"
    config.write_text(
        "drone: {address: '127.0.0.1:7000', vehicle_url: 'udpout://127.0.0.1:9'}\n"
        "controllers:\n  - {id: 3, address: '127.0.0.1:7003'}\n"
        "  - {id: 4, address: '127.0.0.1:7004'}\ninitial_master: 4\nspeedup: 5\n"
    )
    settings = settings_from_args(_drone_args("--config", str(config), "--resolution", "32x16"))
    assert (settings.address, settings.vehicle_url) == ("127.0.0.1:7000", "udpout://127.0.0.1:9")
    assert (settings.controllers, settings.master, settings.speedup) == ((3, 4), 4, 5.0)
    assert settings.resolution == (32, 16)
    assert settings.camera_effects_file is None
    assert settings.tls is not None and settings.tls.identity == DRONE
    counted = settings_from_args(
        _drone_args("--camera-effects-file", str(tmp_path / "c.jsonl"), "--insecure")
    )
    assert counted.camera_effects_file == str(tmp_path / "c.jsonl")
    assert counted.tls is None
    flags = settings_from_args(
        _drone_args(
            "--controllers", "0,1,2", "--address", "127.0.0.1:0", "--certs", str(tmp_path / "certs")
        )
    )
    assert (flags.controllers, flags.master, flags.address) == ((0, 1, 2), 0, "127.0.0.1:0")
    assert flags.tls is not None
    with pytest.raises(
        TlsError, match=r"nowhere/ca\.crt: cannot read the drone TLS files.*--insecure"
    ):
        settings_from_args(_drone_args("--certs", str(tmp_path / "nowhere")))


def test_cli_rejects_bad_handover_file_and_master(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from baton.drone.cli import settings_from_args

    script = tmp_path / "h.txt"
    script.write_text("3 1\n4 9\n")
    with pytest.raises(HandoverScriptError, match=r"h\.txt:2: unknown controller id 9"):
        settings_from_args(_drone_args("--controllers", "0,1", "--handover-file", str(script)))
    with pytest.raises(ValueError, match="--initial-master 5"):
        settings_from_args(_drone_args("--controllers", "0,1", "--initial-master", "5"))
    with pytest.raises(SystemExit):
        _drone_args("--controllers", "0,0")


def test_cli_handover_policy_from_the_config_or_the_flag(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from baton.drone.cli import settings_from_args

    config = tmp_path / "testbed.yaml"
    config.write_text(
        "controllers:\n"
        "  - {id: 0, address: '127.0.0.1:7000', range_m: 500,\n"
        "     location: {latitude_deg: 47.0, longitude_deg: 8.0}}\n"
        "  - {id: 1, address: '127.0.0.1:7001', range_m: 300,\n"
        "     location: {latitude_deg: 47.0, longitude_deg: 8.01}}\n"
        "handover_policy: {name: nearest, margin_m: 20, dwell: 1s}\n"
        "takeover_after: 4s\ntls: {insecure: true}\n"
    )
    settings = settings_from_args(_drone_args("--config", str(config)))
    assert settings.policy is not None
    assert (settings.policy.name, settings.policy.margin_m, settings.policy.dwell_s) == (
        "nearest",
        20.0,
        1.0,
    )
    assert settings.policy.link_lost_after_s == 4.0
    assert settings.stations[1].range_m == 300.0
    assert settings.stations[1].location.longitude_deg == 8.01
    flag = settings_from_args(_drone_args("--config", str(config), "--handover-policy", "none"))
    assert flag.policy is None
    with pytest.raises(ValueError, match="--handover-policy predictive needs --config"):
        settings_from_args(_drone_args("--handover-policy", "predictive", "--insecure"))
    bare = tmp_path / "bare.yaml"
    bare.write_text("controllers: [{id: 0, address: '127.0.0.1:7000'}]\ntls: {insecure: true}\n")
    with pytest.raises(ValueError, match="controller 0 has no location"):
        settings_from_args(_drone_args("--config", str(bare), "--handover-policy", "nearest"))


class _Params:
    """MAVSDK's param plugin on an autopilot that has only ``values``: a read of any
    other is refused as MAVSDK refuses it (ParamError)."""

    def __init__(self, values: dict[str, float]) -> None:
        self.values = values
        self.asked: list[str] = []

    async def get_param_float(self, name: str) -> float:
        self.asked.append(name)
        if name not in self.values:
            raise RuntimeError(f"ParamError: {name}: PARAM_NOT_FOUND")
        return self.values[name]

    async def get_param_int(self, name: str) -> int:
        return round(await self.get_param_float(name))

    async def set_param_float(self, name: str, value: float) -> None:
        self.values[name] = value

    async def set_param_int(self, name: str, value: int) -> None:
        self.values[name] = value


async def test_the_autopilot_s_bounds_read_where_it_has_the_parameters() -> None:
    """A PX4 without GF_MAX_VER_DIST: its speed bound read, no ceiling; with the
    mission's fence, the ceiling the drone sets itself is not asked."""
    mobility = MavsdkMobility("udpin://127.0.0.1:0")
    assert mobility.autopilot_limits() is None  # not read yet
    mobility._param = params = _Params({"MPC_XY_VEL_MAX": 9.0})
    await mobility._read_limits()
    assert mobility.autopilot_limits() == VehicleLimits(9.0, "MPC_XY_VEL_MAX")
    assert params.asked == ["MPC_XY_VEL_MAX", "GF_MAX_VER_DIST"]
    fenced = MavsdkMobility("udpin://127.0.0.1:0", fence=Fence(ceiling_m=50.0))
    fenced._param = params = _Params({"MPC_XY_VEL_MAX": 9.0, "GF_MAX_VER_DIST": 50.0})
    await fenced._read_limits()
    assert fenced.autopilot_limits() == VehicleLimits(9.0, "MPC_XY_VEL_MAX")
    assert params.asked == ["MPC_XY_VEL_MAX"]
    # A mission's fence without a ceiling: the autopilot's own ceiling is its bound.
    open_sky = MavsdkMobility("udpin://127.0.0.1:0", fence=Fence(polygons=(FencePolygon(()),)))
    open_sky._param = params = _Params({"MPC_XY_VEL_MAX": 9.0, "GF_MAX_VER_DIST": 80.0})
    await open_sky._read_limits()
    assert params.asked == ["MPC_XY_VEL_MAX", "GF_MAX_VER_DIST"]
    assert open_sky.autopilot_limits() == VehicleLimits(
        9.0, "MPC_XY_VEL_MAX", 80.0, "GF_MAX_VER_DIST"
    )


async def test_the_fence_sets_its_bits_of_fence_type_and_keeps_the_autopilot_s() -> None:
    """ArduPilot's FENCE_TYPE is a bitmask: the drone's polygon bit is set over the
    altitude and circle bits the autopilot had (3), not written over them."""
    mobility = MavsdkMobility("udpin://127.0.0.1:0")
    mobility._param = params = _Params({"FENCE_TYPE": 3, "FENCE_ACTION": 0, "FENCE_ENABLE": 0})
    await mobility._set_params("autopilot fence", fence_params(True, Fence()))
    assert params.values == {"FENCE_TYPE": 7, "FENCE_ACTION": 1, "FENCE_ENABLE": 1}
