"""The bgkmap client: one class, two transports (gRPC and HTTP JSON), numpy in and out.

:class:`Client` is assembled from the calls that write (``_scans``) and read (``_queries``) a
map, both on the transports of ``_transport``; the map catalogue calls live here."""

from __future__ import annotations

import time
from typing import Any, Dict, List

from ._convert import _info_from_json, _info_from_pb
from ._pb import bgkmap_pb2 as pb
from ._queries import _QueryCalls
from ._scans import _ScanCalls
from ._types import PARAM_NAMES, BgkmapError, _param


class Client(_ScanCalls, _QueryCalls):
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
