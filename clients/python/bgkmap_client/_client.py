"""The bgkmap client: one class, two transports (gRPC and HTTP JSON), numpy in and out."""

from __future__ import annotations

import ipaddress
import json
import math
import os
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from typing import Any, Dict, Iterable, List, Literal, Mapping, Optional, Sequence, Tuple, Union

import grpc
import numpy as np

from ._pb import bgkmap_pb2 as pb
from ._pb import bgkmap_pb2_grpc as pb_grpc


__all__ = [
    "UNKNOWN",
    "FREE",
    "OCCUPIED",
    "STATE_NAMES",
    "PARAM_NAMES",
    "BgkmapError",
    "Client",
    "PointsResult",
    "BoxResult",
    "RaysResult",
    "ExportResult",
    "state_names",
    "state_codes",
]

#: Cell state codes, as in the proto's ``CellState`` enum (``CELL_STATE_UNKNOWN`` = 0, …).
UNKNOWN = 0
FREE = 1
OCCUPIED = 2
#: ``STATE_NAMES[code]`` is the state's name as the HTTP API spells it.
STATE_NAMES: Tuple[str, str, str] = ("unknown", "free", "occupied")
_STATE_CODE = {name: code for code, name in enumerate(STATE_NAMES)}

#: Map parameters, named like ``bgkmap build``'s flags and the proto's ``MapParams`` fields.
PARAM_NAMES: Tuple[str, ...] = (
    "resolution",
    "sf2",
    "ell",
    "free_resolution",
    "ds_resolution",
    "max_range",
    "range_mode",
    "prior_a",
    "prior_b",
    "p_free",
    "p_occ",
    "var_max",
    "sub_cells",
)

#: Parameters that are not floats: ``range_mode`` is a name, ``sub_cells`` a whole number.
_PARAM_TYPES: Dict[str, Any] = {"range_mode": str, "sub_cells": int}


def _param(name: str, value: Any) -> Any:
    """A map parameter as its wire type (``sub_cells`` must be a whole number)."""
    kind = _PARAM_TYPES.get(name, float)
    if kind is int and float(value) != int(value):
        raise TypeError(f"map parameter {name} must be a whole number, not {value!r}")
    return kind(value)


ArrayLike = Union[np.ndarray, Sequence[float], Sequence[Sequence[float]]]
Pose = Tuple[ArrayLike, ArrayLike]

# The server's one mapping between gRPC codes and HTTP statuses (src/api/status.rs), both ways.
_GRPC_TO_HTTP = {
    "OK": 200,
    "INVALID_ARGUMENT": 400,
    "NOT_FOUND": 404,
    "ALREADY_EXISTS": 409,
    "RESOURCE_EXHAUSTED": 429,
    "INTERNAL": 500,
    "UNIMPLEMENTED": 501,
    "UNAVAILABLE": 503,
    "DEADLINE_EXCEEDED": 504,
}
_HTTP_TO_GRPC = {
    400: "INVALID_ARGUMENT",
    404: "NOT_FOUND",
    405: "UNIMPLEMENTED",
    409: "ALREADY_EXISTS",
    412: "FAILED_PRECONDITION",
    # The box query answers 413 where gRPC answers INVALID_ARGUMENT (a box over the cell limit).
    413: "INVALID_ARGUMENT",
    415: "INVALID_ARGUMENT",
    422: "INVALID_ARGUMENT",
    429: "RESOURCE_EXHAUSTED",
    500: "INTERNAL",
    501: "UNIMPLEMENTED",
    503: "UNAVAILABLE",
    504: "DEADLINE_EXCEEDED",
}

_MAX_MESSAGE_BYTES = 64 << 20  # the server's default gRPC message limit


class BgkmapError(Exception):
    """A request the server (or the connection to it) refused.

    Attributes:
        code: the gRPC status code name, e.g. ``"INVALID_ARGUMENT"``, ``"NOT_FOUND"``,
            ``"ALREADY_EXISTS"``, ``"RESOURCE_EXHAUSTED"`` (a full scan queue), ``"UNAVAILABLE"``
            (cannot connect, or the server is shutting down). HTTP answers are mapped to the same
            names with the server's own table, so code is transport-independent.
        message: the server's message (it names the offending field).
        http_status: the HTTP status: the one received over HTTP, or over gRPC the one the server
            uses for this code on its HTTP port (``None`` when there is none, e.g. no connection).
        retry_after: seconds to wait before retrying a busy map, when the server said so.
        transport: ``"grpc"`` or ``"http"``.
    """

    def __init__(
        self,
        code: str,
        message: str,
        *,
        http_status: Optional[int] = None,
        retry_after: Optional[float] = None,
        transport: str = "grpc",
    ) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.http_status = http_status
        self.retry_after = retry_after
        self.transport = transport


class PointsResult(tuple):
    """Answer of :meth:`Client.query_points`: unpacks as ``(probability, variance, state)``.

    Attributes:
        probability: ``float64 (N,)``, the posterior mean occupancy of each point's cell.
        variance: ``float64 (N,)``, its posterior variance.
        state: ``int8 (N,)`` state codes: :data:`UNKNOWN` (0), :data:`FREE` (1),
            :data:`OCCUPIED` (2) — the proto's ``CellState`` numbers; :func:`state_names` turns
            them into ``"unknown"``/``"free"``/``"occupied"``.
        cell: ``int32 (N, 3)``, each point's integer cell key (``floor(x / resolution)``).
        version: number of scans in the map snapshot that answered.
    """

    cell: np.ndarray
    version: int

    def __new__(
        cls, probability: np.ndarray, variance: np.ndarray, state: np.ndarray, cell: np.ndarray, version: int
    ) -> "PointsResult":
        self = super().__new__(cls, (probability, variance, state))
        self.cell = cell
        self.version = version
        return self

    @property
    def probability(self) -> np.ndarray:
        return self[0]

    @property
    def variance(self) -> np.ndarray:
        return self[1]

    @property
    def state(self) -> np.ndarray:
        return self[2]


@dataclass
class BoxResult:
    """Answer of :meth:`Client.query_box`: one entry per answer cube (struct of arrays).

    Attributes:
        min_cell: ``int32 (M, 3)``, minimum cell key of each cube.
        size_cells: ``int64 (M,)``, edge of each cube in cells (``2**coarsen``).
        probability, variance: ``float64 (M,)``.
        state: ``int8 (M,)`` state codes (see :class:`PointsResult`).
        counts: ``{"free": n, "occupied": n, "unknown": n}`` over the whole box.
        version: number of scans in the snapshot that answered.
    """

    min_cell: np.ndarray
    size_cells: np.ndarray
    probability: np.ndarray
    variance: np.ndarray
    state: np.ndarray
    counts: Dict[str, int]
    version: int


@dataclass
class RaysResult:
    """Answer of :meth:`Client.cast_rays`: one entry per ray.

    Attributes:
        blocked: ``bool (N,)``; False means the ray reached its max range ("clear").
        distance: ``float64 (N,)``, metres from the origin to the stopping cell; NaN where clear.
        cell: ``int32 (N, 3)``, the stopping cell's key; zeros where clear (use ``blocked``).
        state: ``int8 (N,)`` state code of the stopping cell; :data:`UNKNOWN` where clear.
        probability: ``float64 (N,)`` of the stopping cell; NaN where clear.
        version: number of scans in the snapshot that answered.
    """

    blocked: np.ndarray
    distance: np.ndarray
    cell: np.ndarray
    state: np.ndarray
    probability: np.ndarray
    version: int


@dataclass
class ExportResult:
    """Answer of :meth:`Client.export`: every cell with evidence, sorted by key (x, y, z).

    Attributes:
        cell: ``int32 (M, 3)`` cell keys; a cell spans ``cell * resolution`` to
            ``(cell + 1) * resolution``.
        probability, variance: ``float64 (M,)``.
        resolution: the map's cell edge in metres.
    """

    cell: np.ndarray
    probability: np.ndarray
    variance: np.ndarray
    resolution: float


def state_names(codes: ArrayLike) -> np.ndarray:
    """State codes (0/1/2) → array of ``"unknown"``/``"free"``/``"occupied"``."""
    return np.asarray(STATE_NAMES, dtype=object)[np.asarray(codes, dtype=np.int64)]


def state_codes(names: Iterable[str]) -> np.ndarray:
    """``"unknown"``/``"free"``/``"occupied"`` names → ``int8`` state codes."""
    return np.fromiter((_STATE_CODE[n] for n in names), dtype=np.int8)


# ---------------------------------------------------------------------------------------------
# Argument conversion (shared by both transports, so both send the same numbers).


def _points_f32(points: ArrayLike, what: str = "points") -> np.ndarray:
    """(N, 3) little-endian float32, C-contiguous: what gRPC carries in ``xyz_f32``."""
    a = np.asarray(points)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must have shape (N, 3), got {a.shape}")
    return np.ascontiguousarray(a, dtype="<f4")


def _vec(v: ArrayLike, n: int, what: str) -> List[float]:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (n,):
        raise ValueError(f"{what} must have {n} values, got shape {a.shape}")
    return [float(x) for x in a]


def _pose(pose: Pose) -> Tuple[List[float], List[float]]:
    try:
        translation, rotation = pose
    except (TypeError, ValueError):
        raise ValueError("pose must be (translation (3,), rotation wxyz (4,))") from None
    return _vec(translation, 3, "pose translation"), _vec(rotation, 4, "pose rotation (w, x, y, z)")


def _frame(frame: str) -> Any:  # a pb.Frame value
    if frame == "world":
        return pb.FRAME_WORLD
    if frame == "sensor":
        return pb.FRAME_SENSOR
    raise ValueError(f"frame must be 'world' or 'sensor', got {frame!r}")


def _state_code(state: Union[str, int]) -> int:
    if isinstance(state, str):
        if state not in _STATE_CODE:
            raise ValueError(f"state must be one of {STATE_NAMES}, got {state!r}")
        return _STATE_CODE[state]
    code = int(state)
    if code not in (UNKNOWN, FREE, OCCUPIED):
        raise ValueError(f"state code must be 0, 1 or 2, got {state!r}")
    return code


def _stop_at(stop_at: str) -> Any:  # a pb.StopAt value
    if stop_at == "occupied":
        return pb.STOP_AT_OCCUPIED
    if stop_at in ("not_free", "unknown"):
        return pb.STOP_AT_NOT_FREE
    raise ValueError(f"stop_at must be 'occupied' or 'not_free', got {stop_at!r}")


def _thresholds(p_free: Optional[float], p_occ: Optional[float], var_max: Optional[float]) -> Dict[str, float]:
    t = {"p_free": p_free, "p_occ": p_occ, "var_max": var_max}
    return {k: float(v) for k, v in t.items() if v is not None}


def _is_loopback(host: str) -> bool:
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _grpc_host(address: str) -> str:
    target = address.split("://", 1)[-1]
    if target.startswith("["):
        return target[1 : target.find("]")]
    return target.rsplit(":", 1)[0]


# ---------------------------------------------------------------------------------------------
# Answer conversion.


def _info_from_pb(m: Any) -> Dict[str, Any]:
    return {
        "map": m.map,
        "params": {n: getattr(m.params, n) for n in PARAM_NAMES if m.params.HasField(n)},
        "version": int(m.version),
        "blocks": int(m.blocks),
        "cells_with_evidence": int(m.cells_with_evidence),
        "queued": int(m.queued),
        "sources": {
            s.source: {
                "received": int(s.received),
                "applied": int(s.applied),
                "duplicates": int(s.duplicates),
                "rejected": int(s.rejected),
                "highest_seq": int(s.highest_seq) if s.HasField("highest_seq") else None,
                "pending": int(s.pending),
                "gaps": int(s.gaps),
                "pruned": int(s.pruned),
                "retracted": int(s.retracted),
                "dropped_points": int(s.dropped_points),
            }
            for s in m.sources
        },
        "scans": int(m.scans),
        "journal_bytes": int(m.journal_bytes),
        "corrupt_blocks": int(m.corrupt_blocks),
        "read_only": m.read_only or None,
    }


def _info_from_json(j: Mapping[str, Any]) -> Dict[str, Any]:
    params = j.get("params", {})
    return {
        "map": j["map"],
        "params": {n: _param(n, params[n]) for n in PARAM_NAMES if n in params},
        "version": int(j["version"]),
        "blocks": int(j["blocks"]),
        "cells_with_evidence": int(j["cells_with_evidence"]),
        "queued": int(j["queued"]),
        "sources": {
            name: {
                "received": int(s["received"]),
                "applied": int(s["applied"]),
                "duplicates": int(s["duplicates"]),
                "rejected": int(s["rejected"]),
                "highest_seq": None if s.get("highest_seq") is None else int(s["highest_seq"]),
                "pending": int(s["pending"]),
                "gaps": int(s["gaps"]),
                "pruned": int(s["pruned"]),
                "retracted": int(s["retracted"]),
                "dropped_points": int(s.get("dropped_points", 0)),
            }
            for name, s in j.get("sources", {}).items()
        },
        "scans": int(j["scans"]),
        "journal_bytes": int(j["journal_bytes"]),
        "corrupt_blocks": int(j["corrupt_blocks"]),
        "read_only": j.get("read_only"),
    }


def _f64(values: Any) -> np.ndarray:
    return np.array(values, dtype=np.float64)


def _cells(values: Any) -> np.ndarray:
    return np.array(values, dtype=np.int32).reshape(-1, 3)


class Client:
    """A connection to a bgkmap server.

    Args:
        grpc_address: ``host:port`` of the gRPC port.
        http_address: ``host:port`` or ``http://host:port`` of the HTTP port; needed for
            ``transport="http"`` and for :meth:`insert_pcd`.
        transport: ``"grpc"`` or ``"http"``: which port the calls use. Both give identical
            numbers: points travel as float32 on both (the HTTP transport rounds them to float32
            before writing JSON), every other number as float64. (Known server issue: the HTTP
            port parses some 17-digit JSON numbers 1 ulp off, so a float64 argument such as a ray
            direction may differ by 1 ulp from what gRPC delivers; see README.)
        timeout: seconds each call may take (``None``: no limit).

    Every method raises :class:`BgkmapError` when the server refuses the request, and
    ``ValueError``/``TypeError`` for arguments of the wrong shape before sending anything.
    The client is a context manager; :meth:`close` closes the gRPC channel.
    """

    def __init__(
        self,
        grpc_address: str = "127.0.0.1:50051",
        http_address: Optional[str] = None,
        transport: Literal["grpc", "http"] = "grpc",
        timeout: Optional[float] = 60.0,
    ) -> None:
        if transport not in ("grpc", "http"):
            raise ValueError(f"transport must be 'grpc' or 'http', got {transport!r}")
        if transport == "http" and not http_address:
            raise ValueError("transport='http' needs http_address")
        self.transport = transport
        self.timeout = timeout
        self.grpc_address = grpc_address
        self._channel: Optional[grpc.Channel] = None
        self._stub: Optional[pb_grpc.MapServiceStub] = None
        self.http_address = http_address
        self._http_base: Optional[str] = None
        self._opener: Optional[urllib.request.OpenerDirector] = None
        if http_address:
            base = http_address if "://" in http_address else f"http://{http_address}"
            self._http_base = base.rstrip("/")
            host = urllib.parse.urlsplit(self._http_base).hostname or ""
            # Never send loopback traffic through an HTTP proxy from the environment.
            handlers = [urllib.request.ProxyHandler({})] if _is_loopback(host) else []
            self._opener = urllib.request.build_opener(*handlers)

    # -- plumbing -----------------------------------------------------------------------------

    def _grpc(self) -> pb_grpc.MapServiceStub:
        if self._stub is None:
            options = [
                ("grpc.max_send_message_length", _MAX_MESSAGE_BYTES),
                ("grpc.max_receive_message_length", _MAX_MESSAGE_BYTES),
            ]
            if _is_loopback(_grpc_host(self.grpc_address)):
                options.append(("grpc.enable_http_proxy", 0))
            self._channel = grpc.insecure_channel(self.grpc_address, options=options)
            self._stub = pb_grpc.MapServiceStub(self._channel)
        return self._stub

    def _call(self, method: str, request: Any) -> Any:
        try:
            return getattr(self._grpc(), method)(request, timeout=self.timeout)
        except grpc.RpcError as e:
            raise _grpc_error(e) from None

    def _http(
        self,
        method: str,
        path: str,
        body: Any = None,
        *,
        raw: Optional[bytes] = None,
        content_type: str = "application/json",
        query: Optional[Mapping[str, Any]] = None,
    ) -> Any:
        if self._http_base is None or self._opener is None:
            raise ValueError("this call needs the HTTP port: pass http_address to Client()")
        url = self._http_base + path
        if query:
            url += "?" + urllib.parse.urlencode(query)
        # NaN/Infinity (in a pose, say) go out as Python writes them; they are not JSON, so the
        # server refuses the body with 400, as it refuses them over gRPC.
        data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
        headers = {"Accept": "application/json"}
        if data is not None:
            headers["Content-Type"] = content_type
        req = urllib.request.Request(url, data=data, method=method, headers=headers)
        try:
            with self._opener.open(req, timeout=self.timeout) as r:
                payload = r.read()
        except urllib.error.HTTPError as e:
            text = e.read().decode("utf-8", "replace")
            try:
                message = json.loads(text)["error"]
            except (ValueError, KeyError, TypeError):
                message = text.strip() or e.reason
            retry = e.headers.get("Retry-After") if e.headers else None
            raise BgkmapError(
                _HTTP_TO_GRPC.get(e.code, "UNKNOWN"),
                str(message),
                http_status=e.code,
                retry_after=float(retry) if retry else None,
                transport="http",
            ) from None
        except urllib.error.URLError as e:
            raise BgkmapError("UNAVAILABLE", f"{url}: {e.reason}", transport="http") from None
        except OSError as e:  # timeouts, resets mid-body
            raise BgkmapError("UNAVAILABLE", f"{url}: {e}", transport="http") from None
        return json.loads(payload) if payload else None

    def _map_path(self, name: str, *rest: str) -> str:
        return "/".join(["/v1/maps", urllib.parse.quote(name, safe=""), *rest])

    def close(self) -> None:
        """Closes the gRPC channel (if one was opened)."""
        if self._channel is not None:
            self._channel.close()
            self._channel = None
            self._stub = None

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def wait_ready(self, timeout: float = 10.0) -> None:
        """Blocks until the server answers on this client's transport, or raises BgkmapError."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                self.list_maps()
                return
            except BgkmapError as e:
                if e.code != "UNAVAILABLE" or time.monotonic() > deadline:
                    raise
            time.sleep(0.05)

    # -- maps ---------------------------------------------------------------------------------

    def create_map(self, name: str, **params: Any) -> Dict[str, Any]:
        """Creates map ``name`` with parameters fixed for its life; returns its info.

        ``params`` are named like ``bgkmap build``'s flags (see :data:`PARAM_NAMES`):
        ``resolution``, ``sf2``, ``ell``, ``free_resolution``, ``ds_resolution``, ``max_range``,
        ``range_mode`` (``"truncate"``/``"drop"``), ``prior_a``, ``prior_b``, ``p_free``,
        ``p_occ``, ``var_max``, ``sub_cells`` (a whole number); unset ones take the server's
        defaults. An existing name raises
        ``BgkmapError`` ``ALREADY_EXISTS``.

        Returns a dict like :meth:`get_map`'s.
        """
        unknown = sorted(set(params) - set(PARAM_NAMES))
        if unknown:
            raise TypeError(f"unknown map parameters {unknown}; known: {list(PARAM_NAMES)}")
        clean: Dict[str, Any] = {k: _param(k, v) for k, v in params.items() if v is not None}
        if self.transport == "grpc":
            req = pb.CreateMapRequest(map=name, params=pb.MapParams(**clean))
            return _info_from_pb(self._call("CreateMap", req))
        return _info_from_json(self._http("PUT", self._map_path(name), clean))

    def list_maps(self) -> List[Dict[str, Any]]:
        """Every map's info (see :meth:`get_map`)."""
        if self.transport == "grpc":
            return [_info_from_pb(m) for m in self._call("ListMaps", pb.ListMapsRequest()).maps]
        return [_info_from_json(m) for m in self._http("GET", "/v1/maps")["maps"]]

    def get_map(self, name: str) -> Dict[str, Any]:
        """Parameters and statistics of one map.

        Returns ``{"map", "params": {name: value, …} (every parameter of PARAM_NAMES),
        "version" (+1 per integrated scan and per merge / retraction / re-posing), "scans" (in
        the map), "blocks", "cells_with_evidence", "queued", "journal_bytes", "corrupt_blocks",
        "read_only" (None, or why ingest is refused), "sources": {source: {"received", "applied",
        "duplicates", "rejected", "highest_seq", "pending", "gaps", "pruned", "retracted",
        "dropped_points"}}}``.
        Unknown maps raise ``BgkmapError`` ``NOT_FOUND``.
        """
        if self.transport == "grpc":
            return _info_from_pb(self._call("GetMap", pb.GetMapRequest(map=name)))
        return _info_from_json(self._http("GET", self._map_path(name)))

    # -- scans --------------------------------------------------------------------------------

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

    # -- queries ------------------------------------------------------------------------------

    def query_points(
        self,
        map: str,
        xyz: ArrayLike,
        p_free: Optional[float] = None,
        p_occ: Optional[float] = None,
        var_max: Optional[float] = None,
    ) -> PointsResult:
        """Occupancy at points.

        Args:
            xyz: ``(N, 3)`` query points, rounded to float32 (the wire format of both
                transports).
            p_free, p_occ, var_max: state thresholds for this query (unset: the map's).
                A cell is free when ``probability < p_free`` and occupied when
                ``probability > p_occ``, each only when ``variance < var_max``; else unknown.

        Returns:
            :class:`PointsResult`, which unpacks as ``(probability, variance, state)``:
            float64 ``(N,)``, float64 ``(N,)`` and int8 ``(N,)`` state codes
            (:data:`UNKNOWN` 0, :data:`FREE` 1, :data:`OCCUPIED` 2); it also has ``.cell``
            (int32 ``(N, 3)`` cell keys) and ``.version``.
        """
        pts = _points_f32(xyz, "xyz")
        th = _thresholds(p_free, p_occ, var_max)
        if self.transport == "grpc":
            req = pb.QueryPointsRequest(map=map, xyz_f32=pts.tobytes())
            if th:
                req.thresholds.CopyFrom(pb.Thresholds(**th))
            r = self._call("QueryPoints", req)
            return PointsResult(
                _f64(r.probability),
                _f64(r.variance),
                np.array(r.state, dtype=np.int8),
                _cells(r.cell),
                int(r.version),
            )
        body: Dict[str, Any] = {"points": pts.astype(np.float64).tolist()}
        if th:
            body["thresholds"] = th
        r = self._http("POST", self._map_path(map, "query", "points"), body)
        res = r["results"]
        return PointsResult(
            _f64([x["probability"] for x in res]),
            _f64([x["variance"] for x in res]),
            state_codes(x["state"] for x in res),
            _cells([x["cell"] for x in res]),
            int(r["version"]),
        )

    def query_box(
        self,
        map: str,
        min: ArrayLike,
        max: ArrayLike,
        state: Optional[Union[str, int]] = None,
        coarsen: int = 0,
        counts_only: bool = False,
        p_free: Optional[float] = None,
        p_occ: Optional[float] = None,
        var_max: Optional[float] = None,
    ) -> BoxResult:
        """Cells of an axis-aligned box ``[min, max]`` (world metres).

        Args:
            state: only cells in this state (``"free"``/``"occupied"``/``"unknown"`` or a code).
            coarsen: aggregate ``2**coarsen`` cells per axis (evidence summed), 0–10.
            counts_only: only the counts per state, no cells.
            p_free, p_occ, var_max: state thresholds (unset: the map's).

        Returns:
            :class:`BoxResult`.
        """
        lo, hi = _vec(min, 3, "min"), _vec(max, 3, "max")
        th = _thresholds(p_free, p_occ, var_max)
        code = None if state is None else _state_code(state)
        if self.transport == "grpc":
            req = pb.QueryBoxRequest(map=map, min=lo, max=hi, coarsen=int(coarsen), counts_only=bool(counts_only))
            if code is not None:
                req.state = code  # type: ignore[assignment]
            if th:
                req.thresholds.CopyFrom(pb.Thresholds(**th))
            r = self._call("QueryBox", req)
            return BoxResult(
                min_cell=_cells(r.min_cell),
                size_cells=np.array(r.size_cells, dtype=np.int64),
                probability=_f64(r.probability),
                variance=_f64(r.variance),
                state=np.array(r.state, dtype=np.int8),
                counts={"free": int(r.free), "occupied": int(r.occupied), "unknown": int(r.unknown)},
                version=int(r.version),
            )
        body: Dict[str, Any] = {"min": lo, "max": hi, "coarsen": int(coarsen), "counts_only": bool(counts_only)}
        if code is not None:
            body["state"] = STATE_NAMES[code]
        if th:
            body["thresholds"] = th
        r = self._http("POST", self._map_path(map, "query", "box"), body)
        cells = r.get("cells", [])
        c = r["counts"]
        return BoxResult(
            min_cell=_cells([x["min_cell"] for x in cells]),
            size_cells=np.array([x["size_cells"] for x in cells], dtype=np.int64),
            probability=_f64([x["probability"] for x in cells]),
            variance=_f64([x["variance"] for x in cells]),
            state=state_codes(x["state"] for x in cells),
            counts={"free": int(c["free"]), "occupied": int(c["occupied"]), "unknown": int(c["unknown"])},
            version=int(r["version"]),
        )

    def cast_rays(
        self,
        map: str,
        origins: ArrayLike,
        directions: ArrayLike,
        max_range: Union[float, ArrayLike],
        stop_at: Literal["occupied", "not_free"] = "occupied",
        p_free: Optional[float] = None,
        p_occ: Optional[float] = None,
        var_max: Optional[float] = None,
    ) -> RaysResult:
        """Casts rays through the map.

        Args:
            origins: ``(N, 3)`` or ``(3,)`` (shared) ray origins, metres (float64).
            directions: ``(N, 3)`` or ``(3,)`` directions (need not be unit length).
            max_range: ``(N,)`` or a scalar, metres.
            stop_at: ``"occupied"`` (first occupied cell) or ``"not_free"`` (first occupied or
                unknown cell).
            p_free, p_occ, var_max: state thresholds (unset: the map's).

        Returns:
            :class:`RaysResult` (``blocked``, ``distance`` NaN where clear, ``cell``, ``state``,
            ``probability``).
        """
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        if o.shape[-1:] != (3,) or o.ndim > 2 or d.shape[-1:] != (3,) or d.ndim > 2:
            raise ValueError(f"origins and directions must be (N, 3) or (3,), got {o.shape} and {d.shape}")
        r = np.asarray(max_range, dtype=np.float64)
        try:
            if r.ndim > 1:
                raise ValueError
            (n,) = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], r.shape) or (1,)
            o, d = np.broadcast_to(o, (n, 3)), np.broadcast_to(d, (n, 3))
            r = np.broadcast_to(r, (n,))
        except ValueError:
            raise ValueError(
                f"origins {o.shape}, directions {d.shape} and max_range {r.shape} do not broadcast to N rays"
            ) from None
        stop = _stop_at(stop_at)
        th = _thresholds(p_free, p_occ, var_max)
        blocked = np.zeros(n, dtype=bool)
        distance = np.full(n, np.nan)
        cell = np.zeros((n, 3), dtype=np.int32)
        state = np.full(n, UNKNOWN, dtype=np.int8)
        probability = np.full(n, np.nan)
        if self.transport == "grpc":
            req = pb.CastRaysRequest(
                map=map,
                rays=[
                    pb.Ray(origin=o[i].tolist(), direction=d[i].tolist(), max_range=float(r[i])) for i in range(n)
                ],
                stop_at=stop,
            )
            if th:
                req.thresholds.CopyFrom(pb.Thresholds(**th))
            resp = self._call("CastRays", req)
            results = [
                (x.blocked, list(x.cell), x.distance, x.state, x.probability) for x in resp.results
            ]
            version = int(resp.version)
        else:
            body: Dict[str, Any] = {
                "rays": [
                    {"origin": o[i].tolist(), "direction": d[i].tolist(), "max_range": float(r[i])} for i in range(n)
                ],
                "stop_at": "occupied" if stop == pb.STOP_AT_OCCUPIED else "not_free",
            }
            if th:
                body["thresholds"] = th
            resp = self._http("POST", self._map_path(map, "query", "rays"), body)
            results = [
                (
                    x["blocked"],
                    x.get("cell"),
                    x.get("distance"),
                    _STATE_CODE[x["state"]] if "state" in x else UNKNOWN,
                    x.get("probability"),
                )
                for x in resp["results"]
            ]
            version = int(resp["version"])
        if len(results) != n:
            raise BgkmapError("INTERNAL", f"asked for {n} rays, got {len(results)} answers")
        for i, (b, c, dist, st, p) in enumerate(results):
            if not b:
                continue
            blocked[i] = True
            cell[i] = c
            distance[i] = dist
            state[i] = st
            probability[i] = p
        return RaysResult(blocked, distance, cell, state, probability, version)

    def export(
        self,
        map: str,
        min: Optional[ArrayLike] = None,
        max: Optional[ArrayLike] = None,
        p_free: Optional[float] = None,
        p_occ: Optional[float] = None,
        var_max: Optional[float] = None,
    ) -> ExportResult:
        """Every cell with evidence (optionally only inside ``[min, max]``), over the gRPC
        ``Export`` stream (gRPC transport only)."""
        if self.transport != "grpc":
            raise NotImplementedError("export is served over gRPC only; use transport='grpc'")
        req = pb.ExportRequest(map=map)
        if (min is None) != (max is None):
            raise ValueError("give both min and max, or neither")
        if min is not None and max is not None:
            req.min.extend(_vec(min, 3, "min"))
            req.max.extend(_vec(max, 3, "max"))
        th = _thresholds(p_free, p_occ, var_max)
        if th:
            req.thresholds.CopyFrom(pb.Thresholds(**th))
        cells: List[np.ndarray] = []
        prob: List[np.ndarray] = []
        var: List[np.ndarray] = []
        resolution = math.nan
        try:
            for chunk in self._grpc().Export(req, timeout=self.timeout):
                cells.append(_cells(chunk.cell))
                prob.append(_f64(chunk.probability))
                var.append(_f64(chunk.variance))
                resolution = float(chunk.resolution)
        except grpc.RpcError as e:
            raise _grpc_error(e) from None
        return ExportResult(
            cell=np.concatenate(cells) if cells else np.zeros((0, 3), dtype=np.int32),
            probability=np.concatenate(prob) if prob else np.zeros(0),
            variance=np.concatenate(var) if var else np.zeros(0),
            resolution=resolution,
        )


def _grpc_error(e: grpc.RpcError) -> BgkmapError:
    code = e.code() if hasattr(e, "code") else None
    name = code.name if code is not None else "UNKNOWN"
    message = (e.details() if hasattr(e, "details") else None) or str(e)
    retry_after = None
    try:
        for k, v in e.trailing_metadata() or ():
            if k == "retry-after-ms":
                retry_after = float(v) / 1000.0
    except Exception:  # noqa: BLE001 - metadata is optional
        pass
    return BgkmapError(
        name, message, http_status=_GRPC_TO_HTTP.get(name), retry_after=retry_after, transport="grpc"
    )
