"""Python client for the bgkmap occupancy map server.

    import numpy as np
    from bgkmap_client import Client

    c = Client("127.0.0.1:50051")  # gRPC; or Client(http_address="127.0.0.1:8080", transport="http")
    c.create_map("office", max_range=8)
    c.insert_scan("office", points, pose=([0, 0, 0], [1, 0, 0, 0]), source="lidar", seq=1)
    p, var, state = c.query_points("office", np.array([[3.0, 0.0, 0.5]]))

See :class:`Client` for every call; states are int codes :data:`UNKNOWN`, :data:`FREE`,
:data:`OCCUPIED` (:func:`state_names` gives their names).
"""

from ._client import Client
from ._types import (
    FREE,
    OCCUPIED,
    PARAM_NAMES,
    STATE_NAMES,
    UNKNOWN,
    BgkmapError,
    BoxResult,
    ExportResult,
    PointsResult,
    RaysResult,
    state_codes,
    state_names,
)

__version__ = "0.1.0"

__all__ = [
    "Client",
    "BgkmapError",
    "PointsResult",
    "BoxResult",
    "RaysResult",
    "ExportResult",
    "UNKNOWN",
    "FREE",
    "OCCUPIED",
    "STATE_NAMES",
    "PARAM_NAMES",
    "state_names",
    "state_codes",
]
