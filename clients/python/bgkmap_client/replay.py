"""``bgkmap-replay``: stream the point clouds of a ROS 1 or ROS 2 bag into a bgkmap map.

    bgkmap-replay sim_structured.bag --map office --grpc 127.0.0.1:50051 \\
        --cloud-topic /selected_pc2_map --pose-topic /robot_pose
    bgkmap-replay run.mcap --map office --zenoh tcp/127.0.0.1:7450 --cloud-topic /points --pose-topic /pose

Bags are read with the ``rosbags`` package (no ROS installation): ROS 1 ``.bag`` files and ROS 2
bag directories. Each ``sensor_msgs/PointCloud2`` on the cloud topic becomes one scan:

- **pose**: the ``geometry_msgs/PoseStamped`` (or ``nav_msgs/Odometry``) on the pose topic
  whose stamp is nearest the cloud's, within ``--max-pose-gap`` seconds; clouds without one are
  skipped and counted. Without ``--pose-topic`` the sensor sits at the origin.
- **frame**: a cloud in the pose's frame (``/map``, leading slashes ignored) keeps its points and
  the pose gives the ray origin; any other cloud is in the sensor frame.
- **identity**: source = ``--source`` (default: the cloud topic), seq = the cloud's header stamp
  in nanoseconds, the rule of bgkmap's ROS 2 bridge, so a bag replayed twice, or over another
  transport, is applied once.

Over gRPC every scan waits for its acknowledgement (``InsertScan``: durable in the server's
journal). Over zenoh it goes to the acknowledged ``bgkmap/<map>/ingest`` query (the same
acknowledgement). The last scan is sent with ``wait_applied``, so when bgkmap-replay returns
every scan it sent is integrated and visible to queries (a map integrates in journal order), and
the summary's ``version`` includes them. With ``--no-ack`` scans are put on
``bgkmap/<map>/scans/<source>`` (congestion control BLOCK; one query at the end makes sure the
puts reached the server before the session closes). Non-finite points are sent: the
server drops and counts them. Prints a JSON summary; ``--dry-run`` prints each scan instead of
sending it.
"""

from __future__ import annotations

import argparse
import bisect
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from ._pb import bgkmap_pb2 as pb

FLOAT32, FLOAT64 = 7, 8
_NS = 1_000_000_000


@dataclass
class StampedPose:
    stamp_ns: int
    frame: str
    translation: Tuple[float, float, float]
    rotation_wxyz: Tuple[float, float, float, float]


@dataclass
class ReplayScan:
    seq: int
    frame: str  # "world" or "sensor"
    pose: StampedPose
    points: np.ndarray  # (N, 3) float32
    pose_gap_ns: int


def _frame_name(name: str) -> str:
    return name[1:] if name.startswith("/") else name


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * _NS + int(header.stamp.nanosec)


def cloud_xyz(msg: Any) -> np.ndarray:
    """(x, y, z) of every point of a PointCloud2, row by row, as float32 (non-finite kept)."""
    if msg.is_bigendian:
        raise ValueError("big-endian point data is not supported")
    fields = {f.name: f for f in msg.fields}
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    rows, cols, step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    out = np.empty((rows * cols, 3), dtype=np.float32)
    for axis, name in enumerate("xyz"):
        f = fields.get(name)
        if f is None or f.datatype not in (FLOAT32, FLOAT64):
            raise ValueError(f"PointCloud2.fields: no FLOAT32/FLOAT64 field {name!r}")
        dtype = np.dtype("<f4" if f.datatype == FLOAT32 else "<f8")
        for r in range(rows):
            start = r * row_step + int(f.offset)
            col = np.ndarray((cols,), dtype=dtype, buffer=data, offset=start, strides=(step,))
            out[r * cols : (r + 1) * cols, axis] = col
    return out


def pose_of(msg: Any) -> StampedPose:
    """A PoseStamped's or an Odometry's pose, rotation as (w, x, y, z)."""
    pose = msg.pose.pose if hasattr(msg, "child_frame_id") else msg.pose
    p, q = pose.position, pose.orientation
    return StampedPose(
        _stamp_ns(msg.header),
        _frame_name(msg.header.frame_id),
        (float(p.x), float(p.y), float(p.z)),
        (float(q.w), float(q.x), float(q.y), float(q.z)),
    )


class PoseTrack:
    """Poses sorted by stamp; the nearest one to a stamp."""

    def __init__(self, poses: Sequence[StampedPose]) -> None:
        self.poses = sorted(poses, key=lambda p: p.stamp_ns)
        self.stamps = [p.stamp_ns for p in self.poses]

    def nearest(self, stamp_ns: int) -> Optional[StampedPose]:
        i = bisect.bisect_left(self.stamps, stamp_ns)
        near = [self.poses[j] for j in (i - 1, i) if 0 <= j < len(self.poses)]
        return min(near, key=lambda p: abs(p.stamp_ns - stamp_ns), default=None)


def read_scans(
    bags: Sequence[Path],
    cloud_topic: str,
    pose_topic: Optional[str],
    max_pose_gap_s: float,
    frame: str = "auto",
) -> Iterator[Tuple[Optional[ReplayScan], str]]:
    """Yields ``(scan, "")`` per cloud, or ``(None, reason)`` for a cloud that is skipped."""
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(b) for b in bags]) as reader:
        clouds = [c for c in reader.connections if c.topic == cloud_topic]
        if not clouds:
            raise SystemExit(f"bgkmap-replay: no topic {cloud_topic!r} in the bag")
        track = PoseTrack([])
        if pose_topic:
            conns = [c for c in reader.connections if c.topic == pose_topic]
            if not conns:
                raise SystemExit(f"bgkmap-replay: no topic {pose_topic!r} in the bag")
            track = PoseTrack([pose_of(reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages(conns)])
        origin = StampedPose(0, "", (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
        for conn, _, raw in reader.messages(clouds):
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = _stamp_ns(msg.header)
            pose = track.nearest(stamp) if pose_topic else StampedPose(stamp, "", origin.translation, origin.rotation_wxyz)
            if pose is None or abs(pose.stamp_ns - stamp) > max_pose_gap_s * _NS:
                yield None, f"cloud stamped {stamp} ns has no pose within {max_pose_gap_s} s"
                continue
            cloud_frame = _frame_name(msg.header.frame_id)
            in_world = cloud_frame in ("", pose.frame) if frame == "auto" else frame == "world"
            points = cloud_xyz(msg)
            yield ReplayScan(stamp, "world" if in_world else "sensor", pose, points, abs(pose.stamp_ns - stamp)), ""


def scan_message(scan: ReplayScan, source: str) -> Any:
    """The ``bgkmap.v1.Scan`` of a replayed scan."""
    return pb.Scan(
        source=source,
        seq=scan.seq,
        world_from_sensor=pb.Pose(translation=list(scan.pose.translation), rotation=list(scan.pose.rotation_wxyz)),
        frame=pb.FRAME_WORLD if scan.frame == "world" else pb.FRAME_SENSOR,
        xyz_f32=np.ascontiguousarray(scan.points, dtype="<f4").tobytes(),
        stamp_nanos=scan.seq,
    )


class GrpcSink:
    def __init__(self, address: str, map_name: str) -> None:
        from ._client import Client

        self.client = Client(address)
        self.map = map_name

    def send(self, scan: Any, wait_applied: bool = False) -> Dict[str, Any]:
        request = pb.InsertScanRequest(map=self.map, scan=scan, wait_applied=wait_applied)
        r = self.client._call("InsertScan", request)
        return {"applied": bool(r.applied), "version": int(r.version)}

    def close(self) -> None:
        self.client.close()


class ZenohSink:
    """Scans over zenoh: the acknowledged ingest query, or puts (``ack=False``)."""

    def __init__(self, endpoint: str, map_name: str, source: str, ack: bool, timeout_s: float = 60.0) -> None:
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.session = zenoh.open(conf)
        self.ack, self.map, self.timeout_s = ack, map_name, timeout_s
        if ack:
            self.entity: Any = self.session.declare_querier(f"bgkmap/{map_name}/ingest", timeout=timeout_s)
        else:
            key = f"bgkmap/{map_name}/scans/{source}"
            self.entity = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + timeout_s
        while not self.entity.matching_status:
            if time.monotonic() > deadline:
                raise SystemExit(f"bgkmap-replay: no bgkmap server answers on zenoh {endpoint} for map {map_name!r}")
            time.sleep(0.01)

    def send(self, scan: Any, wait_applied: bool = False) -> Dict[str, Any]:
        payload = scan.SerializeToString()
        if not self.ack:
            self.entity.put(payload)
            return {"applied": None, "version": None}
        from ._types import BgkmapError

        parameters = "wait_applied" if wait_applied else None
        for reply in self.entity.get(payload=payload, parameters=parameters):
            if reply.ok is not None:
                r = pb.InsertScanResponse.FromString(reply.ok.payload.to_bytes())
                return {"applied": bool(r.applied), "version": int(r.version)}
            code, _, message = reply.err.payload.to_string().partition(": ")
            raise BgkmapError(code, message, transport="zenoh")
        raise BgkmapError("DEADLINE_EXCEEDED", "no reply from bgkmap/<map>/ingest", transport="zenoh")

    def close(self) -> None:
        if not self.ack:
            # Puts have no reply, and closing at once may drop those still queued. A query to the
            # server travels behind them on the same link: its reply means they have arrived.
            key = f"bgkmap/{self.map}/query/points"
            list(self.session.get(key, payload=pb.QueryPointsRequest().SerializeToString(), timeout=self.timeout_s))
        self.session.close()


def _parse(argv: Optional[Sequence[str]]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="bgkmap-replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("bags", nargs="+", type=Path, help="ROS 1 .bag files or ROS 2 bag directories")
    ap.add_argument("--map", required=True, help="map to stream into (must exist unless --create)")
    to = ap.add_mutually_exclusive_group()
    to.add_argument("--grpc", metavar="HOST:PORT", help="bgkmap gRPC address")
    to.add_argument("--zenoh", metavar="ENDPOINT", help="zenoh endpoint of the server, e.g. tcp/127.0.0.1:7450")
    ap.add_argument("--cloud-topic", required=True, help="sensor_msgs/PointCloud2 topic")
    ap.add_argument("--pose-topic", help="geometry_msgs/PoseStamped or nav_msgs/Odometry topic")
    ap.add_argument("--source", help="source name of the scans (default: the cloud topic)")
    ap.add_argument("--max-pose-gap", type=float, default=0.5, help="seconds between a cloud and its pose")
    ap.add_argument("--frame", choices=["auto", "world", "sensor"], default="auto")
    ap.add_argument("--no-ack", action="store_true", help="zenoh: put scans instead of the acknowledged query")
    ap.add_argument("--create", action="store_true", help="create the map (defaults, max range 8 m) over gRPC")
    ap.add_argument("--dry-run", action="store_true", help="print the scans (JSON lines) instead of sending")
    a = ap.parse_args(argv)
    if not a.dry_run and not (a.grpc or a.zenoh):
        ap.error("give --grpc or --zenoh (or --dry-run)")
    if a.create and not a.grpc:
        ap.error("--create needs --grpc")
    return a


def _dry_row(scan: ReplayScan) -> Dict[str, Any]:
    return {
        "seq": scan.seq,
        "frame": scan.frame,
        "translation": scan.pose.translation,
        "rotation": scan.pose.rotation_wxyz,
        "points": len(scan.points),
        "pose_gap_ns": scan.pose_gap_ns,
    }


def _count(summary: Dict[str, Any], ack: Dict[str, Any]) -> None:
    if ack["applied"] is not None:
        summary["applied" if ack["applied"] else "duplicates"] += 1
        summary["version"] = ack["version"]


def main(argv: Optional[Sequence[str]] = None) -> int:
    a = _parse(argv)
    source = a.source or a.cloud_topic
    sink: Any = None
    if a.grpc:
        sink = GrpcSink(a.grpc, a.map)
        if a.create:
            sink.client.create_map(a.map, max_range=8.0)
    elif a.zenoh and not a.dry_run:
        sink = ZenohSink(a.zenoh, a.map, source, ack=not a.no_ack)
    summary: Dict[str, Any] = {"scans": 0, "applied": 0, "duplicates": 0, "skipped": 0, "version": None}
    skipped: List[str] = []
    try:
        # One scan of lookahead: the last one is sent with wait_applied (see the module docs).
        held: Optional[ReplayScan] = None
        for scan, reason in read_scans(a.bags, a.cloud_topic, a.pose_topic, a.max_pose_gap, a.frame):
            if scan is None:
                summary["skipped"] += 1
                skipped.append(reason)
                continue
            summary["scans"] += 1
            if a.dry_run:
                print(json.dumps(_dry_row(scan)))
                continue
            if held is not None:
                _count(summary, sink.send(scan_message(held, source)))
            held = scan
        if held is not None:
            _count(summary, sink.send(scan_message(held, source), wait_applied=True))
    finally:
        if sink is not None:
            sink.close()
    for reason in skipped[:5]:
        print(f"bgkmap-replay: skipped: {reason}", file=sys.stderr)
    if not a.dry_run:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
