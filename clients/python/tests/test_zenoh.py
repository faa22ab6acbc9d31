"""ROS 2 robots and bag replay against the real server over zenoh.

A fake ROS 2 robot is built from public parts only: ``rosbags`` serialises ``PointCloud2``,
``PoseStamped`` and ``TFMessage`` in CDR, and ``eclipse-zenoh`` publishes them under rmw_zenoh
key expressions with the rmw_zenoh attachment, as ``rmw_zenoh_cpp`` would. The server decodes
them with its own codec; the map must equal ``bgkmap build`` of the same points.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import struct
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any, Dict, Iterator, List, Tuple

import numpy as np
import pytest

from conftest import REPO_ROOT, Server, server_binary, start_server


def require_module(name: str) -> Any:
    """Imports `name`; missing: skipped, or failed under BGKMAP_REQUIRE_TOOLS=1 (tests/python.sh)."""
    try:
        return importlib.import_module(name)
    except ImportError as e:
        if os.environ.get("BGKMAP_REQUIRE_TOOLS") == "1":
            pytest.fail(f"{name} is not installed: {e}")
        pytest.skip(f"{name} is not installed")


zenoh = require_module("zenoh")
typesys = require_module("rosbags.typesys")

TS = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
T = TS.types
MAX_RANGE = 8.0
NAN_PER_CLOUD = 5
SAMPLE_BAG = REPO_ROOT.parent / "shared" / "data" / "la3dm" / "sim_structured"


# -- messages ---------------------------------------------------------------------------------


def header(stamp_ns: int, frame: str) -> Any:
    stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def point_cloud(stamp_ns: int, frame: str, points: np.ndarray, names: Tuple[str, str, str] = ("x", "y", "z")) -> bytes:
    """An unorganised cloud with float32 fields at offsets 0, 4, 8 and 16-byte records (PCL's)."""
    PF = T["sensor_msgs/msg/PointField"]
    rec = np.zeros((len(points), 4), dtype="<f4")
    rec[:, :3] = points
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=header(stamp_ns, frame),
        height=1,
        width=len(points),
        fields=[PF(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate(names)],
        is_bigendian=False,
        point_step=16,
        row_step=16 * len(points),
        data=np.frombuffer(rec.tobytes(), dtype=np.uint8),
        is_dense=False,
    )
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))


def ros_pose(t: List[float], q_wxyz: List[float]) -> Any:
    P = T["geometry_msgs/msg/Point"](x=t[0], y=t[1], z=t[2])
    w, x, y, z = q_wxyz
    return P, T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)


def pose_stamped(stamp_ns: int, frame: str, t: List[float], q_wxyz: List[float]) -> bytes:
    p, q = ros_pose(t, q_wxyz)
    msg = T["geometry_msgs/msg/PoseStamped"](
        header=header(stamp_ns, frame), pose=T["geometry_msgs/msg/Pose"](position=p, orientation=q)
    )
    return bytes(TS.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))


def tf_message(stamp_ns: int, parent: str, child: str, t: List[float], q_wxyz: List[float]) -> bytes:
    w, x, y, z = q_wxyz
    tr = T["geometry_msgs/msg/Transform"](
        translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
        rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )
    ts = T["geometry_msgs/msg/TransformStamped"](header=header(stamp_ns, parent), child_frame_id=child, transform=tr)
    return bytes(TS.serialize_cdr(T["tf2_msgs/msg/TFMessage"](transforms=[ts]), "tf2_msgs/msg/TFMessage"))


class FakeRobot:
    """rmw_zenoh publishers: key `<domain>/<topic>/<dds type>/<RIHS01 hash>`, every sample with
    the 33-byte attachment (sequence number, source timestamp, GID)."""

    def __init__(self, session: Any, gid: bytes) -> None:
        self.session, self.gid, self.seq, self.pubs = session, gid, 0, {}

    def publisher(self, topic: str, typename: str) -> Any:
        if topic not in self.pubs:
            pkg, _, name = typename.split("/")
            key = f"0/{topic.strip('/')}/{pkg}::msg::dds_::{name}_/{TS.hash_rihs01(typename)}"
            pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + 30
            while not pub.matching_status:
                assert time.monotonic() < deadline, f"the server never subscribed to {key}"
                time.sleep(0.01)
            self.pubs[topic] = pub
        return self.pubs[topic]

    def publish(self, topic: str, typename: str, payload: bytes) -> None:
        self.seq += 1
        attachment = struct.pack("<qqB16s", self.seq, time.time_ns(), 16, self.gid)
        self.publisher(topic, typename).put(payload, attachment=attachment)


# -- scene ------------------------------------------------------------------------------------


def room_points(origin: np.ndarray) -> np.ndarray:
    """World points of a 10 m × 10 m room (walls, floor) seen from `origin`, within max range."""
    s = np.arange(-5.0, 5.0, 0.07)
    h = np.arange(0.0, 2.5, 0.07)
    walls = []
    for fixed in (-5.0, 5.0):
        a, z = np.meshgrid(s, h, indexing="ij")
        walls.append(np.stack([np.full(a.size, fixed), a.ravel(), z.ravel()], axis=1))
        walls.append(np.stack([a.ravel(), np.full(a.size, fixed), z.ravel()], axis=1))
    fx, fy = np.meshgrid(s[::2], s[::2], indexing="ij")
    walls.append(np.stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)], axis=1))
    pts = np.concatenate(walls)
    return pts[np.linalg.norm(pts - origin, axis=1) < MAX_RANGE - 0.5]


def f32(values: List[float]) -> List[float]:
    """The float64 values of float32 numbers: exactly what a PCD VIEWPOINT reads back."""
    return [float(np.float32(v)) for v in values]


def rotation(q_wxyz: List[float]) -> np.ndarray:
    w, x, y, z = np.array(q_wxyz) / np.linalg.norm(q_wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def sensor_scan(t: List[float], q: List[float], seed: int) -> np.ndarray:
    """The room in the sensor frame (float32), with a few NaN returns mixed in."""
    world = room_points(np.array(t))
    pts = ((world - np.array(t)) @ rotation(q)).astype(np.float32)  # Rᵀ (p − t), row-wise
    nan_rows = np.random.default_rng(seed).choice(len(pts), NAN_PER_CLOUD, replace=False)
    pts[nan_rows, 1] = np.nan
    return pts


def write_pcd(path: Path, points: np.ndarray, viewpoint: List[float]) -> None:
    """A binary PCD (x y z float32) with the pose as VIEWPOINT (t, then q as w x y z)."""
    head = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT {' '.join(repr(v) for v in viewpoint)}\n"
        f"POINTS {len(points)}\nDATA binary\n"
    )
    path.write_bytes(head.encode() + np.ascontiguousarray(points, dtype="<f4").tobytes())


# -- server helpers ---------------------------------------------------------------------------


def peer_session(locator: str) -> Any:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([locator]))
    return zenoh.open(conf)


ROS_CONFIG = """
[zenoh]
enabled = true
listen = ["tcp/127.0.0.1:0"]

[[zenoh.ros]]
map = "robots"
cloud_topic = "/robot1/points"
source = "robot1"
pose = "topic"
pose_topic = "/robot1/pose"

[[zenoh.ros]]
map = "robots"
cloud_topic = "/robot2/cloud"
source = "robot2"
pose = "tf"
"""


@pytest.fixture()
def ros_server(tmp_path: Path) -> Iterator[Server]:
    cfg = tmp_path / "bgkmap.toml"
    cfg.write_text(ROS_CONFIG)
    s = start_server(tmp_path / "data", ["--config", str(cfg)])
    assert s.zenoh_locators, s.stdout_lines
    with s.client() as c:
        c.create_map("robots", max_range=MAX_RANGE)
    yield s
    if s.process.poll() is None:
        s.stop()


def map_json(server: Server, name: str) -> Dict[str, Any]:
    with urllib.request.urlopen(f"http://{server.http_address}/v1/maps/{name}", timeout=30) as r:
        return json.loads(r.read())


def wait_sources(server: Server, name: str, want: Dict[str, int], timeout: float = 120.0) -> Dict[str, Any]:
    """Polls until every source in `want` has received (journaled) or rejected that many scans
    and has none waiting for integration (puts have no reply)."""
    deadline = time.monotonic() + timeout
    while True:
        info = map_json(server, name)
        stats = {s: info["sources"].get(s, {}) for s in want}
        got = {s: st.get("received", 0) + st.get("rejected", 0) for s, st in stats.items()}
        if all(got[s] >= n and stats[s].get("pending", 0) == 0 for s, n in want.items()):
            return info
        assert time.monotonic() < deadline, f"timed out: {got} of {want}; {info['sources']}"
        time.sleep(0.05)


def export_csv(bgkmap_file: Path) -> str:
    out = subprocess.run(
        [str(server_binary()), "export", str(bgkmap_file), "--format", "csv"],
        capture_output=True, text=True, timeout=300, check=True,
    )
    return out.stdout


# -- tests ------------------------------------------------------------------------------------

S = 10**9
# robot1's rotations go to the server as published: any float32 values (the server and `bgkmap
# build` normalise the same numbers). robot2's pass through the /tf chain, which composes
# normalised rotations: exactly unit quaternions keep that exact too.
YAWS = [[1.0, 0.0, 0.0, 0.0], f32([0.8, 0.0, 0.0, 0.6]), f32([0.6, 0.0, 0.0, -0.8])]
UNIT = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.5, 0.5, 0.5, 0.5]]


def test_fake_ros2_robots_feed_the_map_an_offline_build_makes(ros_server: Server, tmp_path: Path) -> None:
    """robot1: clouds in its lidar frame posed by a PoseStamped topic; robot2: clouds posed by
    /tf_static map → odom and /tf odom → lidar. Every message is published twice."""
    session = peer_session(ros_server.zenoh_locators[0])
    r1, r2 = FakeRobot(session, b"\x01" * 16), FakeRobot(session, b"\x02" * 16)
    pcds: List[Path] = []
    odom = [1.0, -0.5, 0.0]  # map → robot2/odom: a translation (composes exactly)
    r2.publish("/tf_static", "tf2_msgs/msg/TFMessage", tf_message(0, "map", "robot2/odom", odom, [1.0, 0.0, 0.0, 0.0]))
    for i in range(3):
        stamp = (100 + i) * S + 250_000_000
        t1, q1 = f32([-1.0 + 0.5 * i, 0.25, 0.75]), YAWS[i]
        t2, q2 = [0.5 * i - 2.0, 1.5, 0.5], UNIT[i]  # robot2's lidar in its odom frame
        t2_map = [a + b for a, b in zip(t2, odom)]
        p1, p2 = sensor_scan(t1, q1, seed=i), sensor_scan(t2_map, q2, seed=10 + i)
        for _ in range(2):
            r1.publish("/robot1/pose", "geometry_msgs/msg/PoseStamped", pose_stamped(stamp, "map", t1, q1))
            r1.publish("/robot1/points", "sensor_msgs/msg/PointCloud2", point_cloud(stamp, "robot1/lidar", p1))
            r2.publish("/tf", "tf2_msgs/msg/TFMessage", tf_message(stamp, "robot2/odom", "robot2/lidar", t2, q2))
            r2.publish("/robot2/cloud", "sensor_msgs/msg/PointCloud2", point_cloud(stamp, "/robot2/lidar", p2))
        write_pcd(tmp_path / f"r1_{i}.pcd", p1, t1 + q1)
        write_pcd(tmp_path / f"r2_{i}.pcd", p2, t2_map + q2)
        pcds += [tmp_path / f"r1_{i}.pcd", tmp_path / f"r2_{i}.pcd"]
    info = wait_sources(ros_server, "robots", {"robot1": 6, "robot2": 6})
    session.close()
    assert info["version"] == 6, info
    for robot in ("robot1", "robot2"):
        s = info["sources"][robot]
        assert (s["applied"], s["duplicates"], s["rejected"]) == (3, 3, 0), (robot, s, ros_server.stderr())
        assert s["dropped_points"] == 3 * NAN_PER_CLOUD, s
        assert s["highest_seq"] == 102 * S + 250_000_000
    assert ros_server.stop() == 0, ros_server.stderr()
    subprocess.run(
        [str(server_binary()), "build", "--out", str(tmp_path / "offline.bgkmap"), "--frame", "sensor",
         "--max-range", str(MAX_RANGE), *map(str, pcds)],
        check=True, capture_output=True, timeout=600,
    )
    live = export_csv(ros_server.data_dir / "robots.bgkmap")
    assert live.count("\n") > 1000
    assert live == export_csv(tmp_path / "offline.bgkmap"), "the ROS 2 map differs from the offline build"


def test_malformed_ros_messages_are_counted_logged_once_and_change_nothing(ros_server: Server) -> None:
    session = peer_session(ros_server.zenoh_locators[0])
    robot = FakeRobot(session, b"\x03" * 16)
    pts = sensor_scan([0.0, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0], seed=3)
    cloud = "sensor_msgs/msg/PointCloud2"
    good = point_cloud(5 * S, "robot1/lidar", pts)
    robot.publish("/robot1/points", cloud, good[: len(good) // 2])  # truncated CDR
    robot.publish("/robot1/points", cloud, good[: len(good) // 3])  # again: counted, not logged
    robot.publish("/robot1/points", cloud, b"\x00\x07\x00\x00" + good[4:])  # not CDR (XCDR2 id)
    robot.publish("/robot1/points", cloud, point_cloud(6 * S, "robot1/lidar", pts, ("x", "y", "intensity")))
    robot.publish("/robot1/points", cloud, point_cloud(0, "robot1/lidar", pts))  # no stamp, no identity
    robot.publish("/robot1/pose", "geometry_msgs/msg/PoseStamped", b"\x00\x01\x00\x00\x01")  # a bad pose
    robot.publish("/robot1/pose", "geometry_msgs/msg/PoseStamped", pose_stamped(7 * S, "map", [0.0, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0]))
    robot.publish("/robot1/points", cloud, point_cloud(7 * S, "robot1/lidar", pts))  # fine
    info = wait_sources(ros_server, "robots", {"robot1": 6})
    session.close()
    s = info["sources"]["robot1"]
    assert (s["rejected"], s["applied"], info["version"]) == (5, 1, 1), (s, ros_server.stderr())
    err = ros_server.stderr()
    assert err.count('source "robot1": cdr: sensor_msgs/PointCloud2') == 1, err  # three faults, one line
    assert "PointCloud2.fields: no field named \"z\"" in err, err
    assert "header.stamp must be after the epoch" in err, err
    assert 'source "robot1": pose: geometry_msgs/PoseStamped' in err, err


@pytest.mark.skipif(not (SAMPLE_BAG / "sim_structured.bag").exists(), reason="sample data not found")
def test_replay_the_sample_bag_over_grpc_and_zenoh(tmp_path: Path) -> None:
    """The la3dm bag: 12 clouds in the map frame, each paired with the /robot_pose nearest in
    time. Over gRPC and over zenoh the maps are identical, and a second replay is all
    duplicates; the poses agree with the PCDs' VIEWPOINTs (6 significant digits)."""
    bag = SAMPLE_BAG / "sim_structured.bag"
    replay = Path(sys.executable).parent / "bgkmap-replay"
    topics = ["--cloud-topic", "/selected_pc2_map", "--pose-topic", "/robot_pose"]

    def run(*args: str) -> List[Dict[str, Any]]:
        out = subprocess.run([str(replay), str(bag), *topics, *args], capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr
        return [json.loads(line) for line in out.stdout.splitlines()]

    scans = run("--map", "x", "--dry-run")
    assert len(scans) == 12 and all(s["frame"] == "world" and s["points"] == 3500 for s in scans)
    for i, s in enumerate(scans, start=1):
        vp = (SAMPLE_BAG / f"sim_structured_{i}.pcd").read_bytes().split(b"VIEWPOINT ")[1].split(b"\n")[0]
        want = [float(v) for v in vp.split()[:3]]
        assert all(math.isclose(a, b, abs_tol=2e-5) for a, b in zip(s["translation"], want)), (i, s, want)
    server = start_server(tmp_path / "data", ["--zenoh-listen", "tcp/127.0.0.1:0"])
    try:
        with server.client() as c:
            [summary] = run("--map", "bag_grpc", "--grpc", server.grpc_address, "--create")
            assert (summary["scans"], summary["applied"], summary["version"]) == (12, 12, 12), summary
            c.create_map("bag_zenoh", max_range=8.0)
            [summary] = run("--map", "bag_zenoh", "--zenoh", server.zenoh_locators[0])
            assert (summary["applied"], summary["version"]) == (12, 12), summary
            [summary] = run("--map", "bag_zenoh", "--zenoh", server.zenoh_locators[0])
            assert (summary["applied"], summary["duplicates"]) == (0, 12), summary
            a, b = c.export("bag_grpc"), c.export("bag_zenoh")
            assert len(a.probability) > 10_000
            assert np.array_equal(a.cell, b.cell) and np.array_equal(a.probability, b.probability)
            assert c.get_map("bag_zenoh")["sources"]["/selected_pc2_map"]["highest_seq"] == scans[-1]["seq"]
    finally:
        assert server.stop() == 0, server.stderr()
