from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Frame(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FRAME_WORLD: _ClassVar[Frame]
    FRAME_SENSOR: _ClassVar[Frame]

class CellState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    CELL_STATE_UNKNOWN: _ClassVar[CellState]
    CELL_STATE_FREE: _ClassVar[CellState]
    CELL_STATE_OCCUPIED: _ClassVar[CellState]

class StopAt(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    STOP_AT_OCCUPIED: _ClassVar[StopAt]
    STOP_AT_NOT_FREE: _ClassVar[StopAt]

class UpdateKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    UPDATE_KIND_CATCH_UP: _ClassVar[UpdateKind]
    UPDATE_KIND_LIVE: _ClassVar[UpdateKind]
    UPDATE_KIND_RESYNC: _ClassVar[UpdateKind]
FRAME_WORLD: Frame
FRAME_SENSOR: Frame
CELL_STATE_UNKNOWN: CellState
CELL_STATE_FREE: CellState
CELL_STATE_OCCUPIED: CellState
STOP_AT_OCCUPIED: StopAt
STOP_AT_NOT_FREE: StopAt
UPDATE_KIND_CATCH_UP: UpdateKind
UPDATE_KIND_LIVE: UpdateKind
UPDATE_KIND_RESYNC: UpdateKind

class MapParams(_message.Message):
    __slots__ = ("resolution", "sf2", "ell", "free_resolution", "ds_resolution", "max_range", "range_mode", "prior_a", "prior_b", "p_free", "p_occ", "var_max", "sub_cells")
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    SF2_FIELD_NUMBER: _ClassVar[int]
    ELL_FIELD_NUMBER: _ClassVar[int]
    FREE_RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    DS_RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_FIELD_NUMBER: _ClassVar[int]
    RANGE_MODE_FIELD_NUMBER: _ClassVar[int]
    PRIOR_A_FIELD_NUMBER: _ClassVar[int]
    PRIOR_B_FIELD_NUMBER: _ClassVar[int]
    P_FREE_FIELD_NUMBER: _ClassVar[int]
    P_OCC_FIELD_NUMBER: _ClassVar[int]
    VAR_MAX_FIELD_NUMBER: _ClassVar[int]
    SUB_CELLS_FIELD_NUMBER: _ClassVar[int]
    resolution: float
    sf2: float
    ell: float
    free_resolution: float
    ds_resolution: float
    max_range: float
    range_mode: str
    prior_a: float
    prior_b: float
    p_free: float
    p_occ: float
    var_max: float
    sub_cells: int
    def __init__(self, resolution: _Optional[float] = ..., sf2: _Optional[float] = ..., ell: _Optional[float] = ..., free_resolution: _Optional[float] = ..., ds_resolution: _Optional[float] = ..., max_range: _Optional[float] = ..., range_mode: _Optional[str] = ..., prior_a: _Optional[float] = ..., prior_b: _Optional[float] = ..., p_free: _Optional[float] = ..., p_occ: _Optional[float] = ..., var_max: _Optional[float] = ..., sub_cells: _Optional[int] = ...) -> None: ...

class CreateMapRequest(_message.Message):
    __slots__ = ("map", "params")
    MAP_FIELD_NUMBER: _ClassVar[int]
    PARAMS_FIELD_NUMBER: _ClassVar[int]
    map: str
    params: MapParams
    def __init__(self, map: _Optional[str] = ..., params: _Optional[_Union[MapParams, _Mapping]] = ...) -> None: ...

class ListMapsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListMapsResponse(_message.Message):
    __slots__ = ("maps",)
    MAPS_FIELD_NUMBER: _ClassVar[int]
    maps: _containers.RepeatedCompositeFieldContainer[MapInfo]
    def __init__(self, maps: _Optional[_Iterable[_Union[MapInfo, _Mapping]]] = ...) -> None: ...

class GetMapRequest(_message.Message):
    __slots__ = ("map",)
    MAP_FIELD_NUMBER: _ClassVar[int]
    map: str
    def __init__(self, map: _Optional[str] = ...) -> None: ...

class SourceStats(_message.Message):
    __slots__ = ("source", "received", "applied", "duplicates", "rejected", "highest_seq", "pending", "gaps", "pruned", "retracted", "dropped_points")
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    RECEIVED_FIELD_NUMBER: _ClassVar[int]
    APPLIED_FIELD_NUMBER: _ClassVar[int]
    DUPLICATES_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    HIGHEST_SEQ_FIELD_NUMBER: _ClassVar[int]
    PENDING_FIELD_NUMBER: _ClassVar[int]
    GAPS_FIELD_NUMBER: _ClassVar[int]
    PRUNED_FIELD_NUMBER: _ClassVar[int]
    RETRACTED_FIELD_NUMBER: _ClassVar[int]
    DROPPED_POINTS_FIELD_NUMBER: _ClassVar[int]
    source: str
    received: int
    applied: int
    duplicates: int
    rejected: int
    highest_seq: int
    pending: int
    gaps: int
    pruned: int
    retracted: int
    dropped_points: int
    def __init__(self, source: _Optional[str] = ..., received: _Optional[int] = ..., applied: _Optional[int] = ..., duplicates: _Optional[int] = ..., rejected: _Optional[int] = ..., highest_seq: _Optional[int] = ..., pending: _Optional[int] = ..., gaps: _Optional[int] = ..., pruned: _Optional[int] = ..., retracted: _Optional[int] = ..., dropped_points: _Optional[int] = ...) -> None: ...

class MapInfo(_message.Message):
    __slots__ = ("map", "params", "version", "blocks", "cells_with_evidence", "queued", "sources", "scans", "journal_bytes", "corrupt_blocks", "read_only")
    MAP_FIELD_NUMBER: _ClassVar[int]
    PARAMS_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    BLOCKS_FIELD_NUMBER: _ClassVar[int]
    CELLS_WITH_EVIDENCE_FIELD_NUMBER: _ClassVar[int]
    QUEUED_FIELD_NUMBER: _ClassVar[int]
    SOURCES_FIELD_NUMBER: _ClassVar[int]
    SCANS_FIELD_NUMBER: _ClassVar[int]
    JOURNAL_BYTES_FIELD_NUMBER: _ClassVar[int]
    CORRUPT_BLOCKS_FIELD_NUMBER: _ClassVar[int]
    READ_ONLY_FIELD_NUMBER: _ClassVar[int]
    map: str
    params: MapParams
    version: int
    blocks: int
    cells_with_evidence: int
    queued: int
    sources: _containers.RepeatedCompositeFieldContainer[SourceStats]
    scans: int
    journal_bytes: int
    corrupt_blocks: int
    read_only: str
    def __init__(self, map: _Optional[str] = ..., params: _Optional[_Union[MapParams, _Mapping]] = ..., version: _Optional[int] = ..., blocks: _Optional[int] = ..., cells_with_evidence: _Optional[int] = ..., queued: _Optional[int] = ..., sources: _Optional[_Iterable[_Union[SourceStats, _Mapping]]] = ..., scans: _Optional[int] = ..., journal_bytes: _Optional[int] = ..., corrupt_blocks: _Optional[int] = ..., read_only: _Optional[str] = ...) -> None: ...

class Pose(_message.Message):
    __slots__ = ("translation", "rotation")
    TRANSLATION_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    translation: _containers.RepeatedScalarFieldContainer[float]
    rotation: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, translation: _Optional[_Iterable[float]] = ..., rotation: _Optional[_Iterable[float]] = ...) -> None: ...

class Scan(_message.Message):
    __slots__ = ("source", "seq", "world_from_sensor", "frame", "xyz_f32", "max_range", "stamp_nanos")
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    WORLD_FROM_SENSOR_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    XYZ_F32_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_FIELD_NUMBER: _ClassVar[int]
    STAMP_NANOS_FIELD_NUMBER: _ClassVar[int]
    source: str
    seq: int
    world_from_sensor: Pose
    frame: Frame
    xyz_f32: bytes
    max_range: float
    stamp_nanos: int
    def __init__(self, source: _Optional[str] = ..., seq: _Optional[int] = ..., world_from_sensor: _Optional[_Union[Pose, _Mapping]] = ..., frame: _Optional[_Union[Frame, str]] = ..., xyz_f32: _Optional[bytes] = ..., max_range: _Optional[float] = ..., stamp_nanos: _Optional[int] = ...) -> None: ...

class InsertScanRequest(_message.Message):
    __slots__ = ("map", "scan", "wait_applied")
    MAP_FIELD_NUMBER: _ClassVar[int]
    SCAN_FIELD_NUMBER: _ClassVar[int]
    WAIT_APPLIED_FIELD_NUMBER: _ClassVar[int]
    map: str
    scan: Scan
    wait_applied: bool
    def __init__(self, map: _Optional[str] = ..., scan: _Optional[_Union[Scan, _Mapping]] = ..., wait_applied: bool = ...) -> None: ...

class InsertScanResponse(_message.Message):
    __slots__ = ("applied", "version", "dropped_points")
    APPLIED_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    DROPPED_POINTS_FIELD_NUMBER: _ClassVar[int]
    applied: bool
    version: int
    dropped_points: int
    def __init__(self, applied: bool = ..., version: _Optional[int] = ..., dropped_points: _Optional[int] = ...) -> None: ...

class InsertScansResponse(_message.Message):
    __slots__ = ("scans", "applied", "duplicates", "version")
    SCANS_FIELD_NUMBER: _ClassVar[int]
    APPLIED_FIELD_NUMBER: _ClassVar[int]
    DUPLICATES_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    scans: int
    applied: int
    duplicates: int
    version: int
    def __init__(self, scans: _Optional[int] = ..., applied: _Optional[int] = ..., duplicates: _Optional[int] = ..., version: _Optional[int] = ...) -> None: ...

class Thresholds(_message.Message):
    __slots__ = ("p_free", "p_occ", "var_max")
    P_FREE_FIELD_NUMBER: _ClassVar[int]
    P_OCC_FIELD_NUMBER: _ClassVar[int]
    VAR_MAX_FIELD_NUMBER: _ClassVar[int]
    p_free: float
    p_occ: float
    var_max: float
    def __init__(self, p_free: _Optional[float] = ..., p_occ: _Optional[float] = ..., var_max: _Optional[float] = ...) -> None: ...

class QueryPointsRequest(_message.Message):
    __slots__ = ("map", "xyz_f32", "thresholds")
    MAP_FIELD_NUMBER: _ClassVar[int]
    XYZ_F32_FIELD_NUMBER: _ClassVar[int]
    THRESHOLDS_FIELD_NUMBER: _ClassVar[int]
    map: str
    xyz_f32: bytes
    thresholds: Thresholds
    def __init__(self, map: _Optional[str] = ..., xyz_f32: _Optional[bytes] = ..., thresholds: _Optional[_Union[Thresholds, _Mapping]] = ...) -> None: ...

class QueryPointsResponse(_message.Message):
    __slots__ = ("probability", "variance", "state", "cell", "version")
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    VARIANCE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    CELL_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    probability: _containers.RepeatedScalarFieldContainer[float]
    variance: _containers.RepeatedScalarFieldContainer[float]
    state: _containers.RepeatedScalarFieldContainer[CellState]
    cell: _containers.RepeatedScalarFieldContainer[int]
    version: int
    def __init__(self, probability: _Optional[_Iterable[float]] = ..., variance: _Optional[_Iterable[float]] = ..., state: _Optional[_Iterable[_Union[CellState, str]]] = ..., cell: _Optional[_Iterable[int]] = ..., version: _Optional[int] = ...) -> None: ...

class QueryBoxRequest(_message.Message):
    __slots__ = ("map", "min", "max", "state", "coarsen", "thresholds", "counts_only")
    MAP_FIELD_NUMBER: _ClassVar[int]
    MIN_FIELD_NUMBER: _ClassVar[int]
    MAX_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    COARSEN_FIELD_NUMBER: _ClassVar[int]
    THRESHOLDS_FIELD_NUMBER: _ClassVar[int]
    COUNTS_ONLY_FIELD_NUMBER: _ClassVar[int]
    map: str
    min: _containers.RepeatedScalarFieldContainer[float]
    max: _containers.RepeatedScalarFieldContainer[float]
    state: CellState
    coarsen: int
    thresholds: Thresholds
    counts_only: bool
    def __init__(self, map: _Optional[str] = ..., min: _Optional[_Iterable[float]] = ..., max: _Optional[_Iterable[float]] = ..., state: _Optional[_Union[CellState, str]] = ..., coarsen: _Optional[int] = ..., thresholds: _Optional[_Union[Thresholds, _Mapping]] = ..., counts_only: bool = ...) -> None: ...

class QueryBoxResponse(_message.Message):
    __slots__ = ("min_cell", "size_cells", "probability", "variance", "state", "free", "occupied", "unknown", "version")
    MIN_CELL_FIELD_NUMBER: _ClassVar[int]
    SIZE_CELLS_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    VARIANCE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    FREE_FIELD_NUMBER: _ClassVar[int]
    OCCUPIED_FIELD_NUMBER: _ClassVar[int]
    UNKNOWN_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    min_cell: _containers.RepeatedScalarFieldContainer[int]
    size_cells: _containers.RepeatedScalarFieldContainer[int]
    probability: _containers.RepeatedScalarFieldContainer[float]
    variance: _containers.RepeatedScalarFieldContainer[float]
    state: _containers.RepeatedScalarFieldContainer[CellState]
    free: int
    occupied: int
    unknown: int
    version: int
    def __init__(self, min_cell: _Optional[_Iterable[int]] = ..., size_cells: _Optional[_Iterable[int]] = ..., probability: _Optional[_Iterable[float]] = ..., variance: _Optional[_Iterable[float]] = ..., state: _Optional[_Iterable[_Union[CellState, str]]] = ..., free: _Optional[int] = ..., occupied: _Optional[int] = ..., unknown: _Optional[int] = ..., version: _Optional[int] = ...) -> None: ...

class Ray(_message.Message):
    __slots__ = ("origin", "direction", "max_range")
    ORIGIN_FIELD_NUMBER: _ClassVar[int]
    DIRECTION_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_FIELD_NUMBER: _ClassVar[int]
    origin: _containers.RepeatedScalarFieldContainer[float]
    direction: _containers.RepeatedScalarFieldContainer[float]
    max_range: float
    def __init__(self, origin: _Optional[_Iterable[float]] = ..., direction: _Optional[_Iterable[float]] = ..., max_range: _Optional[float] = ...) -> None: ...

class CastRaysRequest(_message.Message):
    __slots__ = ("map", "rays", "stop_at", "thresholds")
    MAP_FIELD_NUMBER: _ClassVar[int]
    RAYS_FIELD_NUMBER: _ClassVar[int]
    STOP_AT_FIELD_NUMBER: _ClassVar[int]
    THRESHOLDS_FIELD_NUMBER: _ClassVar[int]
    map: str
    rays: _containers.RepeatedCompositeFieldContainer[Ray]
    stop_at: StopAt
    thresholds: Thresholds
    def __init__(self, map: _Optional[str] = ..., rays: _Optional[_Iterable[_Union[Ray, _Mapping]]] = ..., stop_at: _Optional[_Union[StopAt, str]] = ..., thresholds: _Optional[_Union[Thresholds, _Mapping]] = ...) -> None: ...

class RayResult(_message.Message):
    __slots__ = ("blocked", "cell", "distance", "state", "probability")
    BLOCKED_FIELD_NUMBER: _ClassVar[int]
    CELL_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    blocked: bool
    cell: _containers.RepeatedScalarFieldContainer[int]
    distance: float
    state: CellState
    probability: float
    def __init__(self, blocked: bool = ..., cell: _Optional[_Iterable[int]] = ..., distance: _Optional[float] = ..., state: _Optional[_Union[CellState, str]] = ..., probability: _Optional[float] = ...) -> None: ...

class CastRaysResponse(_message.Message):
    __slots__ = ("results", "version")
    RESULTS_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    results: _containers.RepeatedCompositeFieldContainer[RayResult]
    version: int
    def __init__(self, results: _Optional[_Iterable[_Union[RayResult, _Mapping]]] = ..., version: _Optional[int] = ...) -> None: ...

class ExportRequest(_message.Message):
    __slots__ = ("map", "min", "max", "thresholds")
    MAP_FIELD_NUMBER: _ClassVar[int]
    MIN_FIELD_NUMBER: _ClassVar[int]
    MAX_FIELD_NUMBER: _ClassVar[int]
    THRESHOLDS_FIELD_NUMBER: _ClassVar[int]
    map: str
    min: _containers.RepeatedScalarFieldContainer[float]
    max: _containers.RepeatedScalarFieldContainer[float]
    thresholds: Thresholds
    def __init__(self, map: _Optional[str] = ..., min: _Optional[_Iterable[float]] = ..., max: _Optional[_Iterable[float]] = ..., thresholds: _Optional[_Union[Thresholds, _Mapping]] = ...) -> None: ...

class ExportChunk(_message.Message):
    __slots__ = ("cell", "probability", "variance", "resolution")
    CELL_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    VARIANCE_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    cell: _containers.RepeatedScalarFieldContainer[int]
    probability: _containers.RepeatedScalarFieldContainer[float]
    variance: _containers.RepeatedScalarFieldContainer[float]
    resolution: float
    def __init__(self, cell: _Optional[_Iterable[int]] = ..., probability: _Optional[_Iterable[float]] = ..., variance: _Optional[_Iterable[float]] = ..., resolution: _Optional[float] = ...) -> None: ...

class ScanId(_message.Message):
    __slots__ = ("source", "seq")
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    source: str
    seq: int
    def __init__(self, source: _Optional[str] = ..., seq: _Optional[int] = ...) -> None: ...

class MergeMapRequest(_message.Message):
    __slots__ = ("map", "from_map", "from_file")
    MAP_FIELD_NUMBER: _ClassVar[int]
    FROM_MAP_FIELD_NUMBER: _ClassVar[int]
    FROM_FILE_FIELD_NUMBER: _ClassVar[int]
    map: str
    from_map: str
    from_file: str
    def __init__(self, map: _Optional[str] = ..., from_map: _Optional[str] = ..., from_file: _Optional[str] = ...) -> None: ...

class RetractScansRequest(_message.Message):
    __slots__ = ("map", "scans", "source", "from_stamp_nanos", "to_stamp_nanos")
    MAP_FIELD_NUMBER: _ClassVar[int]
    SCANS_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    FROM_STAMP_NANOS_FIELD_NUMBER: _ClassVar[int]
    TO_STAMP_NANOS_FIELD_NUMBER: _ClassVar[int]
    map: str
    scans: _containers.RepeatedCompositeFieldContainer[ScanId]
    source: str
    from_stamp_nanos: int
    to_stamp_nanos: int
    def __init__(self, map: _Optional[str] = ..., scans: _Optional[_Iterable[_Union[ScanId, _Mapping]]] = ..., source: _Optional[str] = ..., from_stamp_nanos: _Optional[int] = ..., to_stamp_nanos: _Optional[int] = ...) -> None: ...

class ScanPose(_message.Message):
    __slots__ = ("scan", "world_from_sensor")
    SCAN_FIELD_NUMBER: _ClassVar[int]
    WORLD_FROM_SENSOR_FIELD_NUMBER: _ClassVar[int]
    scan: ScanId
    world_from_sensor: Pose
    def __init__(self, scan: _Optional[_Union[ScanId, _Mapping]] = ..., world_from_sensor: _Optional[_Union[Pose, _Mapping]] = ...) -> None: ...

class ReposeScansRequest(_message.Message):
    __slots__ = ("map", "poses")
    MAP_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    map: str
    poses: _containers.RepeatedCompositeFieldContainer[ScanPose]
    def __init__(self, map: _Optional[str] = ..., poses: _Optional[_Iterable[_Union[ScanPose, _Mapping]]] = ...) -> None: ...

class MapChange(_message.Message):
    __slots__ = ("scans", "shared_scans", "blocks_changed", "version")
    SCANS_FIELD_NUMBER: _ClassVar[int]
    SHARED_SCANS_FIELD_NUMBER: _ClassVar[int]
    BLOCKS_CHANGED_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    scans: int
    shared_scans: int
    blocks_changed: int
    version: int
    def __init__(self, scans: _Optional[int] = ..., shared_scans: _Optional[int] = ..., blocks_changed: _Optional[int] = ..., version: _Optional[int] = ...) -> None: ...

class WatchUpdatesRequest(_message.Message):
    __slots__ = ("map", "min", "max", "since_version")
    MAP_FIELD_NUMBER: _ClassVar[int]
    MIN_FIELD_NUMBER: _ClassVar[int]
    MAX_FIELD_NUMBER: _ClassVar[int]
    SINCE_VERSION_FIELD_NUMBER: _ClassVar[int]
    map: str
    min: _containers.RepeatedScalarFieldContainer[float]
    max: _containers.RepeatedScalarFieldContainer[float]
    since_version: int
    def __init__(self, map: _Optional[str] = ..., min: _Optional[_Iterable[float]] = ..., max: _Optional[_Iterable[float]] = ..., since_version: _Optional[int] = ...) -> None: ...

class SensorPose(_message.Message):
    __slots__ = ("version", "source", "seq", "world_from_sensor")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    WORLD_FROM_SENSOR_FIELD_NUMBER: _ClassVar[int]
    version: int
    source: str
    seq: int
    world_from_sensor: Pose
    def __init__(self, version: _Optional[int] = ..., source: _Optional[str] = ..., seq: _Optional[int] = ..., world_from_sensor: _Optional[_Union[Pose, _Mapping]] = ...) -> None: ...

class MapUpdate(_message.Message):
    __slots__ = ("kind", "from_version", "version", "block", "block_edge", "resolution", "poses", "reset")
    KIND_FIELD_NUMBER: _ClassVar[int]
    FROM_VERSION_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    BLOCK_FIELD_NUMBER: _ClassVar[int]
    BLOCK_EDGE_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    RESET_FIELD_NUMBER: _ClassVar[int]
    kind: UpdateKind
    from_version: int
    version: int
    block: _containers.RepeatedScalarFieldContainer[int]
    block_edge: int
    resolution: float
    poses: _containers.RepeatedCompositeFieldContainer[SensorPose]
    reset: bool
    def __init__(self, kind: _Optional[_Union[UpdateKind, str]] = ..., from_version: _Optional[int] = ..., version: _Optional[int] = ..., block: _Optional[_Iterable[int]] = ..., block_edge: _Optional[int] = ..., resolution: _Optional[float] = ..., poses: _Optional[_Iterable[_Union[SensorPose, _Mapping]]] = ..., reset: bool = ...) -> None: ...
