"""The read-only calls: points, boxes and rays against a map snapshot, and the export of
every cell with evidence."""

from __future__ import annotations

import math
from typing import Any, Dict, List, Literal, Optional, Union

import grpc
import numpy as np

from ._convert import _cells, _f64, _points_f32, _state_code, _stop_at, _thresholds, _vec
from ._pb import bgkmap_pb2 as pb
from ._transport import _grpc_error, _Transport
from ._types import (
    STATE_NAMES,
    UNKNOWN,
    _STATE_CODE,
    ArrayLike,
    BgkmapError,
    BoxResult,
    ExportResult,
    PointsResult,
    RaysResult,
    state_codes,
)


class _QueryCalls(_Transport):
    """The :class:`~bgkmap_client.Client` methods that read a map."""


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
