"""The client's vocabulary: cell state codes, map parameter names, the error every call raises
and the answers of the queries. Plain data; imports nothing else of the package."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Iterable, Optional, Sequence, Tuple, Union

import numpy as np

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
