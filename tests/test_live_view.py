"""The live view: a real Foxglove WebSocket server on a free port and a real websocket client.

The client speaks the Foxglove WebSocket protocol by hand (subscribe, then binary message
frames: opcode 1, subscription id u32, timestamp u64 ns, payload), so these tests check the
wire format Foxglove Studio reads, not just our own calls. Timeouts bound waits only.
"""

from __future__ import annotations

import asyncio
import base64
import inspect
import json
import math
import socket
import struct
import threading
from pathlib import Path

import numpy as np
import pytest

from robot.base.errors import ConfigError, DriverError
from robot.base.samples import DepthFrame
from robot.localization.localizer import PlaneReport
from robot.maps.plane_map import load_plane_map
from robot.recording import live_view as lv
from robot.recording import schema as ms

ROOT = Path(__file__).resolve().parents[1]
ARENA = load_plane_map(ROOT / "config" / "maps" / "paper_arena.yaml")
HEADER = struct.Struct("<BIQ")
LAYOUT = ROOT / "docs" / "foxglove-layout.json"
OFFSET_NS = 1_700_000_000_987_654_321  # wall clock minus monotonic clock, fixed for the tests
MOUNTS = [("base_link", "front_link", np.eye(4)), ("front_link", "front_optical_frame", np.eye(4))]


@pytest.fixture(autouse=True)
def fixed_wall_clock():
    old = ms.set_wall_clock(ms.WallClock(offset_ns=OFFSET_NS))
    yield
    ms.set_wall_clock(old)


def wall(t: float) -> int:
    return OFFSET_NS + int(round(t * 1e9))

needs_server = pytest.mark.skipif(lv.live_view_missing() is not None,
                                  reason="the 'live' extra (foxglove-websocket) is not installed")


def arun(coro, timeout: float = 30.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


class Client:
    """A minimal Foxglove WebSocket client."""

    def __init__(self, ws):
        self.ws = ws
        self.channels = {}  # topic -> channel dict
        self.subs = {}  # subscription id -> topic
        self.texts = []

    @classmethod
    async def connect(cls, port: int) -> Client:
        import websockets

        ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[lv.SUBPROTOCOL])
        c = cls(ws)
        info = json.loads(await ws.recv())
        assert info["op"] == "serverInfo" and info["supportedEncodings"] == ["json"]
        adv = json.loads(await ws.recv())
        assert adv["op"] == "advertise"
        c.channels = {ch["topic"]: ch for ch in adv["channels"]}
        return c

    async def subscribe(self, *topics: str) -> None:
        subs = []
        for topic in topics:
            sub_id = len(self.subs) + 1
            self.subs[sub_id] = topic
            subs.append({"id": sub_id, "channelId": self.channels[topic]["id"]})
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    async def next_message(self, timeout: float = 10.0):
        """(topic, timestamp ns, decoded JSON) of the next data message; text ops are kept aside."""
        while True:
            raw = await asyncio.wait_for(self.ws.recv(), timeout)
            if isinstance(raw, str):
                msg = json.loads(raw)
                self.texts.append(msg)
                if msg["op"] == "advertise":
                    self.channels.update({ch["topic"]: ch for ch in msg["channels"]})
                continue
            op, sub, ts = HEADER.unpack_from(raw)
            assert op == 1
            return self.subs[sub], ts, json.loads(raw[HEADER.size:].decode("utf-8"))

    async def close(self) -> None:
        await self.ws.close()


async def until(pred, timeout: float = 10.0, what: str = "condition") -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not pred():
        if loop.time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


def roi_label() -> np.ndarray:
    label = np.full((120, 212), -1, dtype=np.int32)
    label[10:60, 20:100] = 0
    label[60:110, 100:200] = 1
    return label


def decode_png(b64: str) -> np.ndarray:
    import cv2

    bgr = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR)
    return bgr[:, :, ::-1]  # RGB


def depth_frame(width=212, height=120, t=12.5, camera="front") -> DepthFrame:
    depth = (np.arange(width * height, dtype=np.uint32).reshape(height, width) % 6000).astype(np.uint16)
    K = np.array([[100.0, 0, (width - 1) / 2], [0, 100.0, (height - 1) / 2], [0, 0, 1]])
    return DepthFrame(camera, depth, 0.001, K, t_capture=t, frame_number=42)


def layout_topics() -> set:
    """Every topic docs/foxglove-layout.json shows: 3D panel topics, image topics, message paths."""
    layout = json.loads(LAYOUT.read_text())
    topics = set()
    for panel_id, cfg in layout["configById"].items():
        kind = panel_id.split("!")[0]
        if kind == "3D":
            topics |= {t for t, v in cfg["topics"].items() if v.get("visible")}
        elif kind == "Image":
            topics.add(cfg["imageMode"]["imageTopic"])
        elif kind in ("Plot", "StateTransitions"):
            topics |= {p["value"].split(".")[0] for p in cfg["paths"]}
        elif kind == "RawMessages":
            topics.add(cfg["topicPath"].split(".")[0])
    return topics


# The server with a real client  -----------------------------------------------------------------

@needs_server
def test_a_client_gets_the_map_on_subscribe_and_every_channel_decodes():
    async def main():
        live = lv.LiveView("127.0.0.1", 0, cameras=["front"])
        live.publish_map(ARENA, t=1.0)  # before start: kept for later subscribers
        await live.start()
        assert live.port != 0 and live.url == f"ws://127.0.0.1:{live.port}"
        client = await Client.connect(live.port)
        assert set(client.channels) == {"/map", "/tf", "/tf_static", "/pose", "/planes", "/plane_fits", "/cmd",
                                        "/status", "/depth/front", "/roi/front"}
        assert client.channels["/pose"]["schemaName"] == "foxglove.PoseInFrame"
        assert client.channels["/roi/front"]["schemaName"] == "foxglove.CompressedImage"
        assert client.channels["/depth/front"]["schemaName"] == "foxglove.RawImage"
        assert client.channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
        assert all(ch["encoding"] == "json" and ch["schemaEncoding"] == "jsonschema" and json.loads(ch["schema"])
                   for ch in client.channels.values())
        await client.subscribe("/map", "/pose", "/planes", "/cmd", "/roi/front")
        got = {}
        topic, ts, got["/map"] = await client.next_message()
        assert topic == "/map" and ts == wall(1.0)  # the recorder's wall-clock log time
        await until(lambda: live.stats["subscribed_channels"] == 5, what="subscriptions")

        cov = np.diag([4e-6, 9e-6, 1e-4])
        live.publish_pose(12.5, 0.51, 0.49, 3.1, cov, "degraded", "heading std 1.2 deg > 1.0 deg")
        live.publish_planes(12.5, "front", [
            PlaneReport("wall_west", "front", 5321, [1.0, 0.0, 0.0], -0.76, True, "ok"),
            PlaneReport("wall_north", "front", 12, None, None, False, "too few inliers").to_json()])
        live.publish_cmd(12.52, 0.1, -0.05, 0.2, wheel_speeds=[1.0, 2.0, 3.0, 4.0])
        live.publish_roi(12.5, "front", roi_label())
        stamps = {}
        for _ in range(4):
            topic, ts, msg = await client.next_message()
            got[topic], stamps[topic] = msg, ts

        # a second client, later, gets the latched map as soon as it subscribes to it
        late = await Client.connect(live.port)
        await late.subscribe("/map")
        late_map = (await late.next_message())[2]
        stats = live.stats
        await late.close()
        await client.close()
        await live.stop()
        assert not live.active and live.stats["clients"] == 0
        return got, stamps, late_map, stats

    got, stamps, late_map, stats = arun(main())

    m = got["/map"]
    assert [p["id"] for p in m["planes"]] == [p.id for p in ARENA.planes]
    west = next(p for p in m["planes"] if p["id"] == "wall_west")
    np.testing.assert_allclose(west["normal"], [1.0, 0.0, 0.0], atol=1e-9)
    assert west["d"] == pytest.approx(0.25)
    (entity,) = m["entities"]
    assert entity["frame_id"] == "map" and len(entity["lines"]) == 4 and all(ln["type"] == 1 for ln in entity["lines"])
    first = entity["lines"][0]["points"]
    np.testing.assert_allclose([[p["x"], p["y"], p["z"]] for p in first], ARENA.planes[0].polygons[0])
    # each wall is filled too: triangles covering exactly its polygon's area
    assert len(entity["triangles"]) == 4
    pts = np.array([[p["x"], p["y"], p["z"]] for p in entity["triangles"][0]["points"]]).reshape(-1, 3, 3)
    area = sum(0.5 * np.linalg.norm(np.cross(b - a, c - a)) for a, b, c in pts)
    assert area == pytest.approx(ARENA.planes[0].area)
    assert sorted(t["text"] for t in entity["texts"]) == sorted(p.id for p in ARENA.planes)
    assert late_map == m

    pose = got["/pose"]
    assert stamps["/pose"] == wall(12.5)
    assert (pose["x"], pose["y"], pose["phi"]) == (0.51, 0.49, 3.1)
    np.testing.assert_allclose(np.reshape(pose["cov"], (3, 3)), np.diag([4e-6, 9e-6, 1e-4]))
    assert pose["quality"] == "degraded" and pose["reason"].startswith("heading std")
    q = pose["pose"]["orientation"]
    assert 2 * math.atan2(q["z"], q["w"]) == pytest.approx(3.1)
    assert pose["frame_id"] == "map" and pose["timestamp"] == {"sec": wall(12.5) // 10 ** 9, "nsec": wall(12.5) % 10 ** 9}
    assert pose["t"] == 12.5  # the monotonic time stays in the message
    assert pose["pos_std"] == pytest.approx(3e-3) and pose["heading_std_deg"] == pytest.approx(math.degrees(0.01))
    assert pose["quality_level"] == 1

    assert got["/planes"] == {"t": 12.5, "camera": "front", "planes": [
        {"id": "wall_west", "camera": "front", "inliers": 5321, "normal": [1.0, 0.0, 0.0], "d": -0.76, "used": True,
         "reason": "ok"},
        {"id": "wall_north", "camera": "front", "inliers": 12, "normal": None, "d": None, "used": False,
         "reason": "too few inliers"}]}
    assert got["/cmd"] == {"t": 12.52, "vx": 0.1, "vy": -0.05, "wz": 0.2, "wheel_speeds": [1.0, 2.0, 3.0, 4.0]}

    roi = got["/roi/front"]
    assert roi["format"] == "png" and roi["frame_id"] == "front_optical_frame"
    rgb = decode_png(roi["data"])
    assert rgb.shape == (120, 212, 3)
    assert tuple(rgb[30, 50]) == tuple(ms.PALETTE[0]) and tuple(rgb[80, 150]) == tuple(ms.PALETTE[1])
    assert tuple(rgb[0, 0]) == ms.NO_PLANE_RGB
    assert stats["clients"] == 2 and stats["dropped"] == 0 and stats["errors"] == 0


@needs_server
def test_a_topic_has_one_schema_and_one_message_layout_live_and_in_a_recording(tmp_path):
    """One Foxglove layout for a live robot and a replay: what the live view advertises and sends
    is what the recorder registers and writes, topic by topic."""
    pytest.importorskip("mcap")
    from mcap.reader import make_reader

    from robot.recording.reader import read_recording
    from robot.recording.recorder import Recorder

    cov = np.diag([4e-6, 9e-6, 1e-4])
    reports = [PlaneReport("wall_west", "front", 5321, [1.0, 0.0, 0.0], -0.76, True, "ok"),
               PlaneReport("wall_north", "front", 12, None, None, False, "too few inliers")]
    wheels = [1.0, 2.0, 3.0, 4.0]
    frame = depth_frame()
    label = roi_label()
    status = {"quality": "degraded", "cameras": {"front": "streaming"}}

    path = tmp_path / "run.mcap"  # every topic the recorder writes, built as the app builds them
    with Recorder(str(path), min_free_bytes=0) as rec:
        rec.write_config(1.0, "cameras: []\n", "planes: []\n")
        rec.write(ms.TOPIC_MAP, 1.0, ms.map_message(ARENA, 1.0))
        rec.write(ms.TOPIC_TF_STATIC, 1.0, ms.transforms_message(1.0, MOUNTS))
        rec.write_odometry(12.4, ms.odometry_message(12.4, wheels, [0.1, 0.2, 0.3, 0.4], 0.01, 3.2))
        rec.write_depth(12.5, frame)
        rec.write_pose(12.5, 0.51, 0.49, 3.1, cov, "degraded", "heading std 1.2 deg > 1.0 deg")
        rec.write(ms.TOPIC_TF, 12.5, ms.odometry_transforms(12.49, (0.1, 0.0, 0.02), (0.4, 0.5, 3.08)))
        rec.write_planes(12.5, ms.planes_message(12.5, "front", reports, frame_number=7, method="joint",
                                                 coarse=(0.5, 0.5, 3.1), coarse_cov=cov, status="ok",
                                                 accepted=["wall_west"], rejected=[], measurements=[]))
        rec.write(ms.TOPIC_PLANE_FITS, 12.5, ms.plane_fits_message(12.5, "front", reports, ARENA))
        rec.write_roi(12.5, "front", label)
        rec.write_cmd(12.52, ms.cmd_message(12.52, 0.1, -0.05, 0.2, wheels, sent=True, state="following",
                                            scale=1.0, reason=""))
        rec.write_status(12.6, ms.status_message(12.6, status))
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    recorded = {c.topic: (summary.schemas[c.schema_id].name, summary.schemas[c.schema_id].encoding,
                          summary.schemas[c.schema_id].data.decode(), c.message_encoding)
                for c in summary.channels.values()}
    written = {m.topic: m.message for m in read_recording(path) if not m.topic.startswith("/depth/")}
    written["/depth/front"] = json.loads(ms.dumps(ms.encode_depth(frame)))  # the reader gives a DepthFrame back

    async def main():
        live = lv.LiveView("127.0.0.1", 0)
        await live.start(ARENA, cameras=["front"])
        live.publish_static_transforms(1.0, MOUNTS)
        client = await Client.connect(live.port)
        topics = sorted(t for t in client.channels)
        await client.subscribe(*topics)
        sent = {}
        for _ in range(2):  # the latched ones come at once
            topic, _, msg = await client.next_message()
            sent[topic] = msg
        await until(lambda: live.stats["subscribed_channels"] == len(topics), what="subscriptions")
        live.publish_map(ARENA, t=1.0)  # the app publishes at start, with its time
        live.publish_depth(12.5, frame)
        live.publish_pose(12.5, 0.51, 0.49, 3.1, cov, "degraded", "heading std 1.2 deg > 1.0 deg")
        live.publish_tf(12.49, (0.1, 0.0, 0.02), (0.4, 0.5, 3.08))
        live.publish_planes(12.5, "front", reports)
        live.publish_roi(12.5, "front", label)
        live.publish_cmd(12.52, 0.1, -0.05, 0.2, wheels)
        live.publish_status(12.6, status)
        for _ in range(9):  # the map again, and one message on each other channel
            topic, _, msg = await client.next_message()
            sent[topic] = msg
        channels = dict(client.channels)
        await client.close()
        await live.stop()
        return channels, sent

    channels, sent = arun(main())
    advertised = {t: (ch["schemaName"], ch["schemaEncoding"], ch["schema"], ch["encoding"])
                  for t, ch in channels.items()}
    both = set(advertised) & set(recorded)
    assert both == set(advertised) == set(ms.camera_topics(["front"], ms.LIVE_TOPICS))
    assert set(recorded) - set(advertised) == {"/config", "/odometry"}  # replay's inputs, not for viewing
    for topic in sorted(both):
        assert advertised[topic] == recorded[topic], topic
    # the same messages: the live ones are the recorded ones, less what only replay needs
    for topic in sorted(both - {"/planes", "/cmd"}):
        assert sent[topic] == written[topic], topic
    for topic in ("/planes", "/cmd"):
        assert {k: written[topic][k] for k in sent[topic]} == sent[topic], topic
    assert set(written["/planes"]) - set(sent["/planes"]) == {"frame_number", "method", "coarse", "coarse_cov",
                                                             "status", "accepted", "rejected", "measurements"}
    fits = sent["/plane_fits"]["entities"][0]
    assert fits["id"] == "fits/front" and fits["lifetime"] == {"sec": 1, "nsec": 0}
    assert [ln["color"]["g"] > ln["color"]["r"] for ln in fits["lines"]] == [True, False]  # fused green, not red


@needs_server
def test_nothing_is_encoded_for_a_channel_nobody_subscribed(monkeypatch):
    built = []
    for name in ("pose_message", "planes_message", "cmd_message", "roi_message", "map_message", "encode_depth",
                 "transforms_message", "odometry_transforms", "status_message", "plane_fits_message"):
        real = getattr(ms, name)
        monkeypatch.setattr(ms, name, lambda *a, _real=real, _name=name, **k: built.append(_name) or _real(*a, **k))

    async def main():
        live = lv.LiveView("127.0.0.1", 0, cameras=["front"])
        await live.start(ARENA)  # kept, encoded only when a client subscribes to /map
        live.publish_static_transforms(0.0, MOUNTS)  # kept too
        frame = depth_frame()
        for i in range(50):  # no client at all
            live.publish_pose(i, 0.0, 0.0, 0.0, np.eye(3))
            live.publish_roi(i, "front", roi_label())
            live.publish_depth(i, frame)
            live.publish_tf(i, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            live.publish_planes(i, "front", [])
            live.publish_status(i, {"quality": "lost"})
        nobody = list(built)
        client = await Client.connect(live.port)
        await client.subscribe("/cmd")
        await until(lambda: live.stats["subscribed_channels"] == 1, what="subscription")
        for i in range(5):  # a client that watches only the command
            live.publish_pose(i, 0.0, 0.0, 0.0, np.eye(3))
            live.publish_planes(i, "front", [])
            live.publish_roi(i, "front", roi_label())
            live.publish_depth(i, frame)
            live.publish_cmd(i, 0.1, 0.0, 0.0)
        topics = [(await client.next_message())[0] for _ in range(5)]
        await client.close()
        await live.stop()
        return nobody, topics

    nobody, topics = arun(main())
    assert nobody == []
    assert built == ["cmd_message"] * 5 and topics == ["/cmd"] * 5


@needs_server
def test_a_client_that_does_not_keep_up_loses_its_oldest_messages_never_the_caller():
    async def main():
        live = lv.LiveView("127.0.0.1", 0, client_queue=8)
        await live.start()
        client = await Client.connect(live.port)
        await client.subscribe("/pose")
        await until(lambda: live.stats["subscribed_channels"] == 1, what="subscription")
        # 200 publishes with no await in between: the client's writer cannot run, its queue fills
        for i in range(200):
            live.publish_pose(float(i), 0.0, 0.0, 0.0, np.eye(3))
        dropped = live.stats["dropped"]
        ts = [(await client.next_message())[2]["t"] for _ in range(8)]
        await client.close()
        await live.stop()
        return dropped, ts

    dropped, ts = arun(main())
    assert dropped == 192
    assert ts == [float(i) for i in range(192, 200)]  # the newest survive, in order


def test_a_client_queue_is_bounded_in_bytes_too_and_drops_its_oldest():
    async def main():
        box = lv._Outbox(connection=None, limit=100, closed_exc=(), max_bytes=1000)
        for i in range(10):  # depth images: few and big; the message limit alone would hold all of them
            box.push(bytes([i]) * 300)
        return box

    box = arun(main())
    assert box.queued_bytes <= 1000 and box.dropped == 7
    assert [frame[0] for frame in box.items] == [7, 8, 9]  # the newest survive, in order
    assert box.queued_bytes == sum(len(f) for f in box.items)


@needs_server
def test_live_depth_is_decimated_to_a_viewable_width_and_kept_within_its_budget():
    async def main():
        live = lv.LiveView("127.0.0.1", 0, cameras=["front"])
        live.set_depth_budget(4.0)  # 500 kB/s: one 424x240 image (270 kB) a second, after the first two
        await live.start()
        client = await Client.connect(live.port)
        await client.subscribe("/depth/front")
        await until(lambda: live.stats["subscribed_channels"] == 1, what="subscription")
        sent_times = []
        for i in range(30):  # 1 s of frames at 30 fps
            t = 20.0 + i / 30
            before = live.stats["depth_skipped"]
            live.publish_depth(t, depth_frame(848, 480, t=t))
            if live.stats["depth_skipped"] == before:
                sent_times.append(t)
            await until(lambda: "/depth/front" not in live._busy, what="encoding")
        msgs = [(await client.next_message())[2] for _ in sent_times]
        skipped = live.stats["depth_skipped"]
        await client.close()
        await live.stop()
        return msgs, sent_times, skipped

    msgs, sent_times, skipped = arun(main())
    size = ms.depth_message_bytes(424, 240)
    assert len(sent_times) + skipped == 30 and 1 <= len(sent_times) <= (500_000 * (1 + 1) + size) // size
    m = msgs[0]
    assert (m["width"], m["height"], m["step"], m["encoding"], m["decimation"]) == (424, 240, 848, "16UC1", 2)
    back = ms.decode_depth(m)
    assert np.array_equal(back.depth, depth_frame(848, 480).depth[::2, ::2])
    assert [x["t_capture"] for x in msgs] == sent_times


@needs_server
def test_bad_values_are_counted_never_raised_and_other_threads_are_handed_to_the_loop():
    async def main():
        live = lv.LiveView("127.0.0.1", 0, cameras=["front"])
        await live.start()
        client = await Client.connect(live.port)
        await client.subscribe("/pose", "/roi/front")
        await until(lambda: live.stats["subscribed_channels"] == 2, what="subscriptions")
        live.publish_pose(1.0, 0.0, 0.0, 0.0, np.eye(2))  # covariance of the wrong shape
        live.publish_roi(1.0, "front", np.zeros((4, 4), np.float32))  # not a label image
        live.publish_pose(2.0, float("nan"), 0.0, 0.0, np.eye(3))  # NaN: JSON null, not a crash
        t = threading.Thread(target=live.publish_pose, args=(3.0, 1.0, 2.0, 0.5, np.eye(3), "localized"))
        t.start()
        t.join()
        msgs = [(await client.next_message())[2] for _ in range(2)]
        errors = live.stats["errors"]
        await client.close()
        await live.stop()
        return msgs, errors

    msgs, errors = arun(main())
    assert errors == 2
    assert msgs[0]["t"] == 2.0 and msgs[0]["x"] is None
    assert (msgs[1]["t"], msgs[1]["x"], msgs[1]["y"], msgs[1]["quality"]) == (3.0, 1.0, 2.0, "localized")


@needs_server
def test_a_camera_not_named_at_start_gets_its_channel_advertised():
    async def main():
        live = lv.LiveView("127.0.0.1", 0)
        await live.start()
        client = await Client.connect(live.port)
        live.publish_roi(0.0, "left", roi_label())  # unknown yet: advertised, this frame not sent
        while "/roi/left" not in client.channels:
            raw = json.loads(await asyncio.wait_for(client.ws.recv(), 10.0))
            if raw["op"] == "advertise":
                client.channels.update({ch["topic"]: ch for ch in raw["channels"]})
        await client.subscribe("/roi/left")
        await until(lambda: live.stats["subscribed_channels"] == 1, what="subscription")
        live.publish_roi(1.0, "left", roi_label())
        topic, _, msg = await client.next_message()
        await client.close()
        await live.stop()
        return topic, msg

    topic, msg = arun(main())
    assert topic == "/roi/left" and msg["frame_id"] == "left_optical_frame"


@needs_server
def test_a_port_in_use_is_a_driver_error_naming_it():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]

        async def main():
            await lv.LiveView("127.0.0.1", port).start()

        with pytest.raises(DriverError, match=f"cannot listen on 127.0.0.1:{port}"):
            arun(main())


# Pure encoding  ----------------------------------------------------------------------------------

def test_a_wide_label_image_is_decimated_and_keeps_its_colours():
    label = np.full((480, 848), -1, np.int32)
    label[:, 424:] = 13  # wraps around the palette
    rgb = decode_png(base64.b64encode(ms.roi_png(label)).decode())
    assert rgb.shape == (240, 424, 3)
    assert tuple(rgb[100, 300]) == tuple(ms.PALETTE[13 % len(ms.PALETTE)])
    assert tuple(rgb[100, 10]) == ms.NO_PLANE_RGB


# The null path  ----------------------------------------------------------------------------------

def test_the_null_live_view_has_the_same_methods_and_does_nothing():
    public = [n for n, _ in inspect.getmembers(lv.LiveView) if not n.startswith("_")]
    null = lv.NullLiveView()
    for name in public:
        assert hasattr(null, name), name
        real = getattr(lv.LiveView, name)
        if callable(real):
            assert inspect.signature(real) == inspect.signature(getattr(lv.NullLiveView, name)), name

    async def main():
        await null.start(ARENA)
        null.publish_map(ARENA)
        null.publish_pose(0.0, 0.0, 0.0, 0.0, np.eye(3), "lost", "no planes")
        null.publish_planes(0.0, "front", [])
        null.publish_roi(0.0, "front", roi_label())
        null.publish_cmd(0.0, 0.0, 0.0, 0.0)
        null.publish_depth(0.0, depth_frame())
        null.publish_tf(0.0, (0, 0, 0), (0, 0, 0))
        null.publish_static_transforms(0.0, MOUNTS)
        null.publish_status(0.0, {})
        null.set_depth_budget(1.0)
        await null.stop()

    arun(main())
    assert not null.active and null.stats["sent"] == 0


def test_the_app_gets_the_null_view_when_off_and_one_clear_line_when_the_extra_is_missing(monkeypatch):
    assert isinstance(lv.make_live_view(None), lv.NullLiveView)
    if lv.live_view_missing() is None:
        view = lv.make_live_view(9123, cameras=["front"])
        assert isinstance(view, lv.LiveView) and (view.host, view.port) == ("127.0.0.1", 9123)

    def missing():
        raise ImportError("No module named 'foxglove_websocket'")

    monkeypatch.setattr(lv, "_import_foxglove", missing)
    assert "foxglove-websocket is not usable" in lv.live_view_missing()
    assert isinstance(lv.make_live_view(None), lv.NullLiveView)
    with pytest.raises(ConfigError) as e:
        lv.make_live_view(8765)
    msg = str(e.value)
    assert "\n" not in msg and "--live" in msg and "pip install 'planeloc-robot[live]'" in msg


def test_the_layout_shows_only_topics_a_recording_and_the_live_view_both_carry(tmp_path):
    """docs/foxglove-layout.json against a real run of the app in simulation, recorded and served
    live at once: every topic a panel of the layout uses is in the recording and reaches a live
    client, with the schema the panel needs."""
    if lv.live_view_missing() is not None:
        pytest.skip("the 'live' extra (foxglove-websocket) is not installed")
    pytest.importorskip("mcap")
    from robot.app.controller import AppOptions
    from robot.config import load_robot_config
    from robot.recording.reader import read_recording
    from robot.recording.recorder import BackgroundRecorder, Recorder
    from robot.sim.realtime import RealtimeSimSettings, sim_rig

    wanted = layout_topics()
    assert {"/map", "/tf", "/tf_static", "/plane_fits", "/pose", "/status", "/depth/front", "/depth/left",
            "/roi/front", "/roi/left"} <= wanted  # 3D, images, plots and raw messages
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    robot = load_robot_config(ROOT / "config" / "robot.yaml")
    view = lv.make_live_view(port)
    recorder = BackgroundRecorder(Recorder(str(tmp_path / "run.mcap"), min_free_bytes=0), max_queue=1 << 16)
    got = {}
    schemas = {}
    opts = AppOptions(install_signal_handlers=False, status_period=0.2, stop_when_done=False)
    with sim_rig(robot, ARENA, (0.5, 0.5, 0.3), RealtimeSimSettings(fps=10), opts, initial_pose=(0.5, 0.5, 0.3),
                 live_view=view, recorder=recorder) as rig:
        async def client():
            await until(lambda: view.active, timeout=30.0, what="the live view")
            c = await Client.connect(port)
            assert wanted <= set(c.channels), wanted - set(c.channels)  # every camera channel advertised at start
            schemas.update({t: c.channels[t]["schemaName"] for t in wanted})
            await c.subscribe(*sorted(wanted))
            while set(got) != wanted:  # each topic once; the hang guard is the timeout below
                topic, _, msg = await c.next_message(30.0)
                got.setdefault(topic, msg)
            await c.close()
            rig.app.request_stop("test done")

        async def main():
            task = asyncio.get_running_loop().create_task(client())
            rc = await rig.app.run()
            await asyncio.wait_for(task, 5.0)
            return rc

        assert asyncio.run(asyncio.wait_for(main(), 120.0)) == 0
    recorded = {m.topic for m in read_recording(tmp_path / "run.mcap")}
    assert wanted <= recorded, wanted - recorded
    assert schemas["/depth/front"] == "foxglove.RawImage" and schemas["/map"] == "foxglove.SceneUpdate"
    assert schemas["/tf"] == "foxglove.FrameTransforms" and schemas["/pose"] == "foxglove.PoseInFrame"
    # what the panels read is there
    assert abs(got["/pose"]["x"] - 0.5) < 0.01 and got["/pose"]["pos_std"] > 0
    assert got["/pose"]["quality_level"] in (0, 1, 2)
    assert {(f["parent_frame_id"], f["child_frame_id"]) for f in got["/tf"]["transforms"]} == {
        ("map", "odom"), ("odom", "base_link")}
    assert ("base_link", "left_link") in {(f["parent_frame_id"], f["child_frame_id"])
                                          for f in got["/tf_static"]["transforms"]}
    depth = ms.decode_depth(got["/depth/front"])
    assert depth.depth.shape == (got["/depth/front"]["height"], got["/depth/front"]["width"])
    assert (depth.depth > 0).mean() > 0.5  # the simulated walls, in millimetres
    img = decode_png(got["/roi/front"]["data"])
    assert img.shape[0] > 10 and (img.reshape(-1, 3).max(axis=1) > 0).mean() > 0.2  # walls are coloured
    assert "quality" in got["/status"] and "cameras" in got["/status"]
