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
from robot.localization.localizer import PlaneReport
from robot.maps.plane_map import load_plane_map
from robot.recording import live_view as lv

ROOT = Path(__file__).resolve().parents[1]
ARENA = load_plane_map(ROOT / "config" / "maps" / "paper_arena.yaml")
HEADER = struct.Struct("<BIQ")

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


# The server with a real client  -----------------------------------------------------------------

@needs_server
def test_a_client_gets_the_map_on_subscribe_and_every_channel_decodes():
    async def main():
        live = lv.LiveView("127.0.0.1", 0, cameras=["front"])
        live.publish_map(ARENA, t=1.0)  # before start: kept for later subscribers
        await live.start()
        assert live.port != 0 and live.url == f"ws://127.0.0.1:{live.port}"
        client = await Client.connect(live.port)
        assert set(client.channels) >= {"/map", "/pose", "/planes", "/cmd", "/roi/front"}
        assert client.channels["/pose"]["schemaName"] == "foxglove.PoseInFrame"
        assert client.channels["/roi/front"]["schemaName"] == "foxglove.CompressedImage"
        assert all(ch["encoding"] == "json" and ch["schemaEncoding"] == "jsonschema" and json.loads(ch["schema"])
                   for ch in client.channels.values())
        await client.subscribe("/map", "/pose", "/planes", "/cmd", "/roi/front")
        got = {}
        topic, ts, got["/map"] = await client.next_message()
        assert topic == "/map" and ts == 1_000_000_000
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
    assert sorted(t["text"] for t in entity["texts"]) == sorted(p.id for p in ARENA.planes)
    assert late_map == m

    pose = got["/pose"]
    assert stamps["/pose"] == 12_500_000_000
    assert (pose["x"], pose["y"], pose["phi"]) == (0.51, 0.49, 3.1)
    np.testing.assert_allclose(np.reshape(pose["cov"], (3, 3)), np.diag([4e-6, 9e-6, 1e-4]))
    assert pose["quality"] == "degraded" and pose["reason"].startswith("heading std")
    q = pose["pose"]["orientation"]
    assert 2 * math.atan2(q["z"], q["w"]) == pytest.approx(3.1)
    assert pose["frame_id"] == "map" and pose["timestamp"] == {"sec": 12, "nsec": 500_000_000}

    assert got["/planes"] == {"t": 12.5, "camera": "front", "planes": [
        {"id": "wall_west", "camera": "front", "inliers": 5321, "used": True, "reason": "ok"},
        {"id": "wall_north", "camera": "front", "inliers": 12, "used": False, "reason": "too few inliers"}]}
    assert got["/cmd"] == {"t": 12.52, "vx": 0.1, "vy": -0.05, "wz": 0.2, "wheel_speeds": [1.0, 2.0, 3.0, 4.0]}

    roi = got["/roi/front"]
    assert roi["format"] == "png" and roi["frame_id"] == "front"
    rgb = decode_png(roi["data"])
    assert rgb.shape == (120, 212, 3)
    assert tuple(rgb[30, 50]) == tuple(lv.PALETTE[0]) and tuple(rgb[80, 150]) == tuple(lv.PALETTE[1])
    assert tuple(rgb[0, 0]) == lv.NO_PLANE_RGB
    assert stats["clients"] == 2 and stats["dropped"] == 0 and stats["errors"] == 0


@needs_server
def test_nothing_is_encoded_for_a_channel_nobody_subscribed(monkeypatch):
    built = []
    for name in ("pose_message", "planes_message", "cmd_message", "roi_message", "map_message"):
        real = getattr(lv, name)
        monkeypatch.setattr(lv, name, lambda *a, _real=real, _name=name, **k: built.append(_name) or _real(*a, **k))

    async def main():
        live = lv.LiveView("127.0.0.1", 0, cameras=["front"])
        await live.start(ARENA)  # kept, encoded only when a client subscribes to /map
        for i in range(50):  # no client at all
            live.publish_pose(i, 0.0, 0.0, 0.0, np.eye(3))
            live.publish_roi(i, "front", roi_label())
        nobody = list(built)
        client = await Client.connect(live.port)
        await client.subscribe("/cmd")
        await until(lambda: live.stats["subscribed_channels"] == 1, what="subscription")
        for i in range(5):  # a client that watches only the command
            live.publish_pose(i, 0.0, 0.0, 0.0, np.eye(3))
            live.publish_planes(i, "front", [])
            live.publish_roi(i, "front", roi_label())
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
    assert topic == "/roi/left" and msg["frame_id"] == "left"


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
    rgb = decode_png(base64.b64encode(lv.roi_png(label)).decode())
    assert rgb.shape == (240, 424, 3)
    assert tuple(rgb[100, 300]) == tuple(lv.PALETTE[13 % len(lv.PALETTE)])
    assert tuple(rgb[100, 10]) == lv.NO_PLANE_RGB


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


@needs_server
def test_the_running_app_publishes_pose_and_roi_images_of_its_frames():
    from robot.app.controller import AppOptions
    from robot.config import load_robot_config
    from robot.sim.realtime import RealtimeSimSettings, sim_rig

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    robot = load_robot_config(ROOT / "config" / "robot.yaml")
    view = lv.make_live_view(port)
    got = {}
    opts = AppOptions(install_signal_handlers=False, status_period=0.2, stop_when_done=False)
    with sim_rig(robot, ARENA, (0.5, 0.5, 0.3), RealtimeSimSettings(fps=10), opts, initial_pose=(0.5, 0.5, 0.3),
                 live_view=view) as rig:
        async def client():
            await asyncio.sleep(1.0)
            c = await Client.connect(port)
            for _ in range(50):
                if "/roi/front" in c.channels and "/pose" in c.channels:
                    break
                try:
                    await c.next_message(0.1)
                except asyncio.TimeoutError:
                    pass
            await c.subscribe("/pose", "/roi/front")
            while len(got) < 2:
                topic, _, msg = await c.next_message(10.0)
                got[topic] = msg
            await c.close()
            rig.app.request_stop("test done")

        async def main():
            task = asyncio.get_running_loop().create_task(client())
            rc = await rig.app.run()
            await asyncio.wait_for(task, 5.0)
            return rc

        assert asyncio.run(asyncio.wait_for(main(), 40.0)) == 0
    assert abs(got["/pose"]["x"] - 0.5) < 0.01
    img = decode_png(got["/roi/front"]["data"])
    assert img.shape[0] > 10 and (img.reshape(-1, 3).max(axis=1) > 0).mean() > 0.2  # walls are coloured
