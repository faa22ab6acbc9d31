"""The calls that change a map: scan ingest (one scan, a stream of scans, a PCD upload) and
the exact operations (merge, retract, re-pose)."""

from __future__ import annotations

import os
from typing import Any, Dict, Iterable, Literal, Mapping, Optional, Tuple, Union

import numpy as np

from ._convert import _frame, _points_f32, _pose
from ._pb import bgkmap_pb2 as pb
from ._transport import _Transport
from ._types import ArrayLike, BgkmapError, Pose


class _ScanCalls(_Transport):
    """The :class:`~bgkmap_client.Client` methods that write to a map."""


    def _scan_pb(
        self,
        points: ArrayLike,
        pose: Pose,
        source: str,
        seq: int,
        frame: str,
        max_range: Optional[float],
    ) -> Any:
        t, r = _pose(pose)
        scan = pb.Scan(
            source=source,
            seq=int(seq),
            world_from_sensor=pb.Pose(translation=t, rotation=r),
            frame=_frame(frame),
            xyz_f32=_points_f32(points).tobytes(),
        )
        if max_range is not None:
            scan.max_range = float(max_range)
        return scan

    def _scan_json(
        self,
        points: ArrayLike,
        pose: Pose,
        source: str,
        seq: int,
        frame: str,
        max_range: Optional[float],
    ) -> Tuple[Dict[str, Any], int]:
        t, r = _pose(pose)
        _frame(frame)
        pts = _points_f32(points)
        # JSON has no NaN/Infinity: drop non-finite points here and count them as dropped, as the
        # server does for a scan sent over gRPC.
        finite = np.isfinite(pts).all(axis=1)
        dropped = int((~finite).sum())
        if dropped:
            pts = pts[finite]  # none left: the server refuses the empty scan (400)
        body: Dict[str, Any] = {
            "source": source,
            "seq": int(seq),
            "pose": {"translation": t, "rotation": r},
            "frame": frame,
            "points": pts.astype(np.float64).tolist(),
        }
        if max_range is not None:
            body["max_range"] = float(max_range)
        return body, dropped

    def insert_scan(
        self,
        map: str,
        points: ArrayLike,
        pose: Pose,
        source: str,
        seq: int,
        frame: Literal["world", "sensor"] = "world",
        max_range: Optional[float] = None,
        wait_applied: bool = True,
    ) -> Dict[str, Any]:
        """Inserts one scan and waits until the server has integrated it (or, with
        ``wait_applied=False``, only until it is durable in the map's journal — faster).

        Args:
            map: map name.
            points: ``(N, 3)`` points (sent as float32). Non-finite points are dropped.
            pose: ``(translation (3,), rotation (4,))``: the sensor pose in the world, rotation
                as a unit quaternion ``(w, x, y, z)``; the translation is the sensor origin.
            source, seq: the scan's identity. A ``(source, seq)`` the map already holds is not
                applied again (``applied`` False).
            frame: ``"world"`` (points in the map frame) or ``"sensor"``
                (``p_world = rotation · p + translation``).
            max_range: the sensor's own maximum range (m), capped by the map's.
            wait_applied: answer once the scan is integrated and visible to queries
                (read-your-writes); otherwise once it is durable.

        Returns:
            ``{"applied": bool, "version": int (the map version when answered; with
            wait_applied it includes the scan), "dropped_points": int}``.
        """
        if self.transport == "grpc":
            req = pb.InsertScanRequest(
                map=map, scan=self._scan_pb(points, pose, source, seq, frame, max_range), wait_applied=wait_applied
            )
            r = self._call("InsertScan", req)
            return {"applied": bool(r.applied), "version": int(r.version), "dropped_points": int(r.dropped_points)}
        body, dropped = self._scan_json(points, pose, source, seq, frame, max_range)
        query = {"wait_applied": "true" if wait_applied else "false"}
        r = self._http("POST", self._map_path(map, "scans"), body, query=query)
        return {
            "applied": bool(r["applied"]),
            "version": int(r["version"]),
            "dropped_points": int(r["dropped_points"]) + dropped,
        }

    def insert_scans(
        self, map: str, scans: Iterable[Mapping[str, Any]], wait_applied: bool = True
    ) -> Dict[str, int]:
        """Inserts many scans in order: over gRPC one ``InsertScans`` stream, over HTTP one
        request each.

        Args:
            scans: mappings with :meth:`insert_scan`'s keyword arguments (``points``, ``pose``,
                ``source``, ``seq``, optionally ``frame``, ``max_range``).

        Returns:
            ``{"scans", "applied", "duplicates", "version"}``. A refused scan raises
            ``BgkmapError`` whose message starts with ``request i:``; the scans before it are
            durable (later ones may be too: resending is safe, duplicates are not applied twice).
        """
        if self.transport == "grpc":

            def requests() -> Iterable[Any]:
                for s in scans:
                    yield pb.InsertScanRequest(
                        map=map,
                        scan=self._scan_pb(
                            s["points"], s["pose"], s["source"], s["seq"], s.get("frame", "world"), s.get("max_range")
                        ),
                        wait_applied=wait_applied,
                    )

            r = self._call("InsertScans", requests())
            return {
                "scans": int(r.scans),
                "applied": int(r.applied),
                "duplicates": int(r.duplicates),
                "version": int(r.version),
            }
        out = {"scans": 0, "applied": 0, "duplicates": 0, "version": 0}
        for i, s in enumerate(scans):
            try:
                ack = self.insert_scan(map, wait_applied=wait_applied, **s)
            except BgkmapError as e:
                raise BgkmapError(
                    e.code,
                    f"request {i}: {e.message}",
                    http_status=e.http_status,
                    retry_after=e.retry_after,
                    transport=e.transport,
                ) from None
            out["scans"] += 1
            out["applied" if ack["applied"] else "duplicates"] += 1
            out["version"] = ack["version"]
        return out

    def insert_pcd(
        self,
        map: str,
        pcd: Union[bytes, str, "os.PathLike[str]"],
        source: str,
        seq: int,
        frame: Literal["world", "sensor"] = "world",
        max_range: Optional[float] = None,
        wait_applied: bool = True,
    ) -> Dict[str, Any]:
        """Uploads a PCD file (bytes or a path) as one scan over HTTP, whatever the transport.

        The sensor pose is the file's ``VIEWPOINT`` line (read as float32 by the server).
        Returns what :meth:`insert_scan` returns.
        """
        if isinstance(pcd, bytes):
            data = pcd
        else:
            with open(pcd, "rb") as f:
                data = f.read()
        query: Dict[str, Any] = {
            "source": source,
            "seq": int(seq),
            "frame": frame,
            "wait_applied": "true" if wait_applied else "false",
        }
        if max_range is not None:
            query["max_range"] = repr(float(max_range))
        r = self._http(
            "POST", self._map_path(map, "scans"), raw=data, content_type="application/x-pcd", query=query
        )
        return {"applied": bool(r["applied"]), "version": int(r["version"]), "dropped_points": int(r["dropped_points"])}

    # -- exact map operations -----------------------------------------------------------------

    def _change(self, method: str, request: Any, path: str, body: Mapping[str, Any]) -> Dict[str, int]:
        if self.transport == "grpc":
            r = self._call(method, request)
            return {
                "scans": int(r.scans),
                "shared_scans": int(r.shared_scans),
                "blocks_changed": int(r.blocks_changed),
                "version": int(r.version),
            }
        j = self._http("POST", path, body)
        return {k: int(j[k]) for k in ("scans", "shared_scans", "blocks_changed", "version")}

    def merge_map(self, map: str, from_map: Optional[str] = None, from_file: Optional[str] = None) -> Dict[str, int]:
        """Adds another map's evidence (another map of the server, or a map file on the server)
        exactly; scans both hold are counted once. Raises ``FAILED_PRECONDITION`` when that
        cannot be done exactly (e.g. shared scans whose raw points were pruned).

        Returns ``{"scans", "shared_scans", "blocks_changed", "version"}``.
        """
        if (from_map is None) == (from_file is None):
            raise ValueError("give exactly one of from_map and from_file")
        body = {"from_map": from_map} if from_map is not None else {"from_file": from_file}
        return self._change("MergeMap", pb.MergeMapRequest(map=map, **body), self._map_path(map, "merge"), body)

    def retract_scans(
        self,
        map: str,
        scans: Optional[Iterable[Tuple[str, int]]] = None,
        source: Optional[str] = None,
        from_stamp_nanos: Optional[int] = None,
        to_stamp_nanos: Optional[int] = None,
    ) -> Dict[str, int]:
        """Removes scans exactly — the listed ``(source, seq)`` ones, or every scan of ``source``
        and/or with ``from_stamp_nanos <= stamp < to_stamp_nanos``.
        """
        ids = [(str(s), int(q)) for s, q in (scans or [])]
        body: Dict[str, Any] = {}
        if ids:
            body["scans"] = [{"source": s, "seq": q} for s, q in ids]
        if source is not None:
            body["source"] = source
        if from_stamp_nanos is not None:
            body["from_stamp_nanos"] = int(from_stamp_nanos)
        if to_stamp_nanos is not None:
            body["to_stamp_nanos"] = int(to_stamp_nanos)
        req = pb.RetractScansRequest(
            map=map,
            scans=[pb.ScanId(source=s, seq=q) for s, q in ids],
            source=source or "",
            **{k: body[k] for k in ("from_stamp_nanos", "to_stamp_nanos") if k in body},
        )
        return self._change("RetractScans", req, self._map_path(map, "retract"), body)

    def repose_scans(self, map: str, poses: Iterable[Tuple[str, int, Pose]]) -> Dict[str, int]:
        """Re-integrates scans under corrected poses ``(source, seq, (translation, rotation))``,
        exactly as if they had been sent with those poses.
        """
        items = [(str(s), int(q), _pose(p)) for s, q, p in poses]
        req = pb.ReposeScansRequest(
            map=map,
            poses=[
                pb.ScanPose(scan=pb.ScanId(source=s, seq=q), world_from_sensor=pb.Pose(translation=t, rotation=r))
                for s, q, (t, r) in items
            ],
        )
        body = {
            "poses": [
                {"source": s, "seq": q, "pose": {"translation": t, "rotation": r}} for s, q, (t, r) in items
            ]
        }
        return self._change("ReposeScans", req, self._map_path(map, "repose"), body)
