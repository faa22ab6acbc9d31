"""Argument conversion (shared by both transports, so both send the same numbers) and answer
conversion (protobuf or JSON map info into one dict shape)."""

from __future__ import annotations

from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

import numpy as np

from ._pb import bgkmap_pb2 as pb
from ._types import FREE, OCCUPIED, PARAM_NAMES, STATE_NAMES, UNKNOWN, _STATE_CODE, ArrayLike, Pose, _param


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
