"""End-to-end tests of bgkmap_client against the real server binary, over both transports,
plus grpcurl and curl against the same server.

Scene: a wall on the plane x = 3 (y ∈ [-1, 1], z ∈ [0, 1.5]) and a floor z = 0 in front of it,
seen by a sensor near the origin. Every scan goes into two maps, one over gRPC and one over
HTTP, and every answer must be bit-identical between the maps and between the transports.
"""

from __future__ import annotations

import base64
import json
import math
import subprocess
from pathlib import Path
from typing import Any, Dict, List

import grpc
import numpy as np
import pytest

from bgkmap_client import (
    FREE,
    OCCUPIED,
    PARAM_NAMES,
    UNKNOWN,
    BgkmapError,
    Client,
    PointsResult,
    state_names,
)
from bgkmap_client._pb import bgkmap_pb2 as pb

from conftest import Server, require_tool, start_server

MAX_RANGE = 8.0
IDENTITY = [1.0, 0.0, 0.0, 0.0]


def yaw(theta: float) -> List[float]:
    """Unit quaternion (w, x, y, z) of a rotation by theta about z."""
    return [math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)]


def grid(*axes: np.ndarray) -> np.ndarray:
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))


def wall_and_floor(step: float = 0.05) -> np.ndarray:
    """World points: wall x = 3 and floor z = 0 (x ∈ [0.5, 2.9])."""
    ys = np.arange(-1.0, 1.0 + 1e-9, step)
    wall = grid(np.array([3.0]), ys, np.arange(0.0, 1.5 + 1e-9, step))
    floor = grid(np.arange(0.5, 2.9 + 1e-9, 2 * step), ys[::2], np.array([0.0]))
    return np.concatenate([wall, floor]).astype(np.float32)


def scans() -> List[Dict[str, Any]]:
    """Three world-frame scans from different origins and one sensor-frame scan (yawed 30°)."""
    pts = wall_and_floor()
    out: List[Dict[str, Any]] = []
    for seq, origin in enumerate([[0.0, 0.0, 0.5], [0.0, 0.3, 0.5], [-0.2, -0.2, 0.6]], start=1):
        out.append(dict(points=pts, pose=(origin, IDENTITY), source="lidar", seq=seq))
    # The same wall seen from a sensor at (0.1, -0.3, 0.7) yawed by 30°: sensor-frame points.
    t = np.array([0.1, -0.3, 0.7])
    th = math.radians(30)
    rot = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]])
    sensor_pts = ((pts.astype(np.float64) - t) @ rot).astype(np.float32)  # rotᵀ · (p - t)
    out.append(dict(points=sensor_pts, pose=(t.tolist(), yaw(th)), source="cam", seq=7, frame="sensor"))
    return out


def query_grid() -> np.ndarray:
    """Query points all over the scene (plus a few of interest first)."""
    special = np.array(
        [
            [3.0, 0.0, 0.5],  # on the wall
            [1.5, 0.0, 0.5],  # seen through
            [6.0, 0.0, 0.5],  # behind the wall
            [0.05, 0.05, 0.05],
        ]
    )
    rng = np.random.default_rng(7)
    rand = rng.uniform([-0.5, -1.5, -0.2], [4.0, 1.5, 1.7], size=(3000, 3))
    return np.concatenate([special, rand]).astype(np.float32)


def assert_points_equal(a: PointsResult, b: PointsResult) -> None:
    for name in ("probability", "variance", "state", "cell"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        assert np.array_equal(x, y), f"{name} differs at {np.flatnonzero(x != y)[:10]}"


def assert_rays_equal(a: Any, b: Any) -> None:
    for name in ("blocked", "distance", "cell", "state", "probability"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=name in ("distance", "probability")), name


def assert_box_equal(a: Any, b: Any) -> None:
    for name in ("min_cell", "size_cells", "probability", "variance", "state"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.counts == b.counts


# ---------------------------------------------------------------------------------------------
# Maps filled once for the session: "wall_g" over gRPC, "wall_h" over HTTP.


@pytest.fixture(scope="module")
def filled(grpc_client: Client, http_client: Client) -> Dict[str, Any]:
    grpc_client.create_map("wall_g", max_range=MAX_RANGE)
    http_client.create_map("wall_h", max_range=MAX_RANGE)
    acks: Dict[str, List[Dict[str, Any]]] = {"g": [], "h": []}
    for s in scans():
        acks["g"].append(grpc_client.insert_scan("wall_g", **s))
        acks["h"].append(http_client.insert_scan("wall_h", **s))
    return acks


def test_create_list_get(grpc_client: Client, http_client: Client) -> None:
    g = grpc_client.create_map("cg", max_range=6, resolution=0.2, range_mode="drop", sub_cells=0)
    h = http_client.create_map("ch", max_range=6, resolution=0.2, range_mode="drop", sub_cells=0)
    assert g["map"] == "cg" and h["map"] == "ch"
    assert set(g["params"]) == set(PARAM_NAMES), g["params"]
    assert g["params"]["max_range"] == 6.0 and g["params"]["resolution"] == 0.2
    assert g["params"]["range_mode"] == "drop"
    assert g["params"]["sub_cells"] == 0 and isinstance(g["params"]["sub_cells"], int)
    assert g["params"]["p_free"] == 0.3 and g["params"]["ell"] == 0.2  # defaults filled in
    assert {k: v for k, v in g.items() if k != "map"} == {k: v for k, v in h.items() if k != "map"}
    assert g["version"] == 0 and g["sources"] == {}

    for c in (grpc_client, http_client):
        names = [m["map"] for m in c.list_maps()]
        assert "cg" in names and "ch" in names
        assert c.get_map("cg") == g
        assert c.get_map("ch") == h
    assert grpc_client.list_maps() == http_client.list_maps()

    with pytest.raises(BgkmapError) as e:
        grpc_client.create_map("cg")
    assert (e.value.code, e.value.http_status) == ("ALREADY_EXISTS", 409)
    with pytest.raises(BgkmapError) as e:
        http_client.create_map("cg")
    assert (e.value.code, e.value.http_status) == ("ALREADY_EXISTS", 409)
    for c in (grpc_client, http_client):
        with pytest.raises(BgkmapError) as e:
            c.get_map("no-such-map")
        assert (e.value.code, e.value.http_status) == ("NOT_FOUND", 404), e.value
        with pytest.raises(BgkmapError) as e:
            c.create_map("bad-params", ell=-1.0)
        assert (e.value.code, e.value.http_status) == ("INVALID_ARGUMENT", 400), e.value
        assert "ell" in e.value.message
        with pytest.raises(BgkmapError) as e:
            c.create_map("bad-params", sub_cells=6)
        assert (e.value.code, e.value.http_status) == ("INVALID_ARGUMENT", 400), e.value
        assert "sub_cells" in e.value.message
        assert c.create_map(f"defaults-{c.transport}")["params"]["sub_cells"] == 8
    with pytest.raises(TypeError):
        grpc_client.create_map("x", no_such_param=1)


def test_insert_acks(filled: Dict[str, Any], grpc_client: Client, http_client: Client) -> None:
    assert filled["g"] == filled["h"]
    assert [a["applied"] for a in filled["g"]] == [True] * 4
    assert [a["version"] for a in filled["g"]] == [1, 2, 3, 4]
    assert all(a["dropped_points"] == 0 for a in filled["g"])
    g, h = grpc_client.get_map("wall_g"), grpc_client.get_map("wall_h")
    assert g["version"] == h["version"] == 4
    assert g["cells_with_evidence"] == h["cells_with_evidence"] > 0
    assert g["blocks"] == h["blocks"] > 0
    assert g["sources"] == h["sources"]
    assert g["sources"]["lidar"]["applied"] == 3 and g["sources"]["lidar"]["highest_seq"] == 3
    assert g["sources"]["cam"]["applied"] == 1 and g["sources"]["cam"]["highest_seq"] == 7


def test_query_points_equal_across_maps_and_transports(
    filled: Dict[str, Any], grpc_client: Client, http_client: Client
) -> None:
    q = query_grid()
    gg = grpc_client.query_points("wall_g", q)
    gh = grpc_client.query_points("wall_h", q)
    hg = http_client.query_points("wall_g", q)
    hh = http_client.query_points("wall_h", q)
    for other in (gh, hg, hh):
        assert_points_equal(gg, other)
        assert other.version == 4
    prob, var, state = gg  # unpacks as a 3-tuple
    assert prob.dtype == np.float64 and var.dtype == np.float64 and state.dtype == np.int8
    assert prob.shape == var.shape == state.shape == (len(q),) and gg.cell.shape == (len(q), 3)
    # The scene makes sense: wall occupied, the space in front free, behind the wall unknown.
    # (With four scans the wall cell itself sits just under the default p_occ of 0.7.)
    assert list(state_names(state[1:3])) == ["free", "unknown"]
    assert prob[0] > 0.6 and var[0] < 0.1
    assert state[1] == FREE and prob[1] < 0.3
    assert state[2] == UNKNOWN and prob[2] == 0.5
    assert np.array_equal(gg.cell[0], [30, 0, 5])
    assert np.array_equal(gg.cell, np.floor(q.astype(np.float64) / 0.1).astype(np.int32))
    assert (state == FREE).sum() > 100 and (state == OCCUPIED).sum() > 10

    # Per-query thresholds, same on both transports.
    a = grpc_client.query_points("wall_g", q, p_free=0.45, p_occ=0.55, var_max=1.0)
    b = http_client.query_points("wall_h", q, p_free=0.45, p_occ=0.55, var_max=1.0)
    assert_points_equal(a, b)
    assert np.array_equal(a.probability, gg.probability)
    assert not np.array_equal(a.state, gg.state)
    assert list(state_names(a.state[:3])) == ["occupied", "free", "unknown"]
    # Empty query.
    for c in (grpc_client, http_client):
        e = c.query_points("wall_g", np.zeros((0, 3)))
        assert e.probability.shape == (0,) and e.cell.shape == (0, 3)


def test_duplicate_scan_changes_nothing(filled: Dict[str, Any], grpc_client: Client, http_client: Client) -> None:
    q = query_grid()
    before = grpc_client.query_points("wall_g", q)
    info = grpc_client.get_map("wall_g")
    s = scans()[1]
    for c in (grpc_client, http_client):
        ack = c.insert_scan("wall_g", **s)
        assert ack == {"applied": False, "version": 4, "dropped_points": 0}
    # A different scan under a used (source, seq) is a duplicate too: nothing is applied.
    moved = dict(s, points=s["points"] + np.float32(0.5))
    assert grpc_client.insert_scan("wall_g", **moved)["applied"] is False
    after = http_client.query_points("wall_g", q)
    assert_points_equal(before, after)
    now = grpc_client.get_map("wall_g")
    assert now["version"] == info["version"] == 4
    assert now["cells_with_evidence"] == info["cells_with_evidence"]
    assert now["sources"]["lidar"]["duplicates"] == info["sources"]["lidar"]["duplicates"] + 3


def test_query_box_agrees(filled: Dict[str, Any], grpc_client: Client, http_client: Client) -> None:
    lo, hi = [2.5, -0.5, 0.0], [3.4, 0.5, 1.0]
    answers = []
    cases: List[Dict[str, Any]] = [
        {},
        {"state": "occupied"},
        {"state": FREE},
        {"coarsen": 2},
        {"counts_only": True},
        {"p_occ": 0.9, "var_max": 50.0},
    ]
    for kwargs in cases:
        gg = grpc_client.query_box("wall_g", lo, hi, **kwargs)
        for other in (
            http_client.query_box("wall_g", lo, hi, **kwargs),
            grpc_client.query_box("wall_h", lo, hi, **kwargs),
            http_client.query_box("wall_h", lo, hi, **kwargs),
        ):
            assert_box_equal(gg, other)
            assert other.version == gg.version == 4
        answers.append((kwargs, gg))
    full = answers[0][1]
    n = len(full.probability)
    assert n == sum(full.counts.values()) > 0
    assert full.min_cell.shape == (n, 3) and np.all(full.size_cells == 1)
    assert full.counts["occupied"] > 0 and full.counts["free"] > 0
    occ = answers[1][1]
    assert np.all(occ.state == OCCUPIED) and len(occ.state) == full.counts["occupied"]
    free = answers[2][1]
    assert np.all(free.state == FREE) and len(free.state) == full.counts["free"]
    coarse = answers[3][1]
    assert np.all(coarse.size_cells == 4) and np.all(coarse.min_cell % 4 == 0)
    counts = answers[4][1]
    assert counts.counts == full.counts and counts.probability.shape == (0,)


def test_cast_rays_agrees(filled: Dict[str, Any], grpc_client: Client, http_client: Client) -> None:
    n = 24
    ang = np.linspace(-math.pi, math.pi, n, endpoint=False)
    # Short decimals: see test_http_parses_json_numbers_exactly for why not cos/sin as they come.
    directions = np.round(np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], axis=1), 6)
    origins = np.array([0.0, 0.0, 0.5])
    ranges = np.full(n, 6.0)
    ranges[0] = 0.5
    res = {}
    for stop in ("occupied", "not_free"):
        gg = grpc_client.cast_rays("wall_g", origins, directions, ranges, stop_at=stop)
        for other in (
            http_client.cast_rays("wall_g", origins, directions, ranges, stop_at=stop),
            grpc_client.cast_rays("wall_h", origins, directions, ranges, stop_at=stop),
            http_client.cast_rays("wall_h", origins, directions, ranges, stop_at=stop),
        ):
            assert_rays_equal(gg, other)
        res[stop] = gg
    r = res["occupied"]
    ahead = np.flatnonzero(np.abs(ang) < 0.2)  # rays straight at the wall
    assert len(ahead) > 0
    assert r.blocked[ahead].all()
    assert np.all(np.abs(r.distance[ahead] - 3.0) < 0.5), r.distance[ahead]
    assert np.all(r.state[ahead] == OCCUPIED) and np.all(r.probability[ahead] > 0.7)
    assert np.all(r.cell[ahead, 0] >= 28)
    back = np.flatnonzero(np.abs(ang) > 2.5)  # away from the wall: nothing there
    assert not r.blocked[back].any()
    assert np.isnan(r.distance[back]).all() and np.isnan(r.probability[back]).all()
    assert np.all(r.cell[back] == 0) and np.all(r.state[back] == UNKNOWN)
    # Stopping at the first cell that is not free stops no later than at the first occupied one.
    nf = res["not_free"]
    assert nf.blocked.sum() >= r.blocked.sum()
    both = r.blocked & nf.blocked
    assert np.all(nf.distance[both] <= r.distance[both])
    # Per-ray origins and a scalar max range broadcast the same way on both transports.
    o = np.tile(origins, (n, 1))
    assert_rays_equal(
        grpc_client.cast_rays("wall_g", o, directions, 6.0), http_client.cast_rays("wall_g", o, directions, 6.0)
    )


def test_http_parses_json_numbers_exactly(filled: Dict[str, Any], grpc_client: Client, http_client: Client) -> None:
    """Any float64 sent over HTTP must reach the server as the same float64 gRPC carries."""
    n = 24
    ang = np.linspace(-math.pi, math.pi, n, endpoint=False)
    directions = np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], axis=1)  # 17-digit decimals
    for stop in ("occupied", "not_free"):
        assert_rays_equal(
            grpc_client.cast_rays("wall_g", [0.0, 0.0, 0.5], directions, 6.0, stop_at=stop),
            http_client.cast_rays("wall_g", [0.0, 0.0, 0.5], directions, 6.0, stop_at=stop),
        )


def test_insert_scans_stream_matches_single_inserts(filled: Dict[str, Any], grpc_client: Client, http_client: Client) -> None:
    grpc_client.create_map("stream_g", max_range=MAX_RANGE)
    http_client.create_map("stream_h", max_range=MAX_RANGE)
    batch = scans()
    batch.append(batch[0])  # a duplicate inside the stream
    sg = grpc_client.insert_scans("stream_g", batch)
    sh = http_client.insert_scans("stream_h", batch)
    assert sg == sh == {"scans": 5, "applied": 4, "duplicates": 1, "version": 4}
    q = query_grid()
    ref = grpc_client.query_points("wall_g", q)
    assert_points_equal(ref, grpc_client.query_points("stream_g", q))
    assert_points_equal(ref, http_client.query_points("stream_h", q))
    # A bad scan in the middle: the earlier ones stay applied, the error names the request.
    grpc_client.create_map("stream_bad")
    bad = [batch[0], dict(batch[1], pose=([0.0, 0.0, 0.5], [2.0, 0.0, 0.0, 0.0])), batch[2]]
    for c, name in ((grpc_client, "stream_bad"), (http_client, "stream_bad")):
        with pytest.raises(BgkmapError) as e:
            c.insert_scans(name, bad)
        assert e.value.code == "INVALID_ARGUMENT" and e.value.message.startswith("request 1: "), e.value
    assert grpc_client.get_map("stream_bad")["version"] == 1


def test_export_matches_queries(filled: Dict[str, Any], grpc_client: Client, http_client: Client) -> None:
    eg = grpc_client.export("wall_g")
    eh = grpc_client.export("wall_h")
    assert np.array_equal(eg.cell, eh.cell) and np.array_equal(eg.probability, eh.probability)
    assert np.array_equal(eg.variance, eh.variance)
    assert eg.resolution == 0.1
    info = grpc_client.get_map("wall_g")
    assert len(eg.cell) == info["cells_with_evidence"] > 0
    order = np.lexsort((eg.cell[:, 2], eg.cell[:, 1], eg.cell[:, 0]))
    assert np.array_equal(order, np.arange(len(order))), "export is sorted by key"
    centres = ((eg.cell + 0.5) * eg.resolution).astype(np.float32)
    for c in (grpc_client, http_client):
        q = c.query_points("wall_g", centres)
        assert np.array_equal(q.cell, eg.cell)
        assert np.array_equal(q.probability, eg.probability)
        assert np.array_equal(q.variance, eg.variance)
    part = grpc_client.export("wall_g", min=[2.5, -0.5, 0.0], max=[3.4, 0.5, 1.0])
    assert 0 < len(part.cell) < len(eg.cell)
    with pytest.raises(NotImplementedError):
        http_client.export("wall_g")


def test_large_map_export_chunks_and_big_queries(grpc_client: Client, http_client: Client) -> None:
    """Over 65 536 cells: Export sends several chunks in key order; queries over the gRPC
    inline-points limit (10 000) agree with HTTP."""
    xs = np.arange(-6.0, 6.0, 0.1)
    floor = grid(xs, xs, np.array([0.0])).astype(np.float32)
    grpc_client.create_map("big")
    assert grpc_client.insert_scan("big", floor, ([0.0, 0.0, 1.0], IDENTITY), "s", 1)["applied"]
    cells = grpc_client.get_map("big")["cells_with_evidence"]
    assert cells > 65_536
    chunks = list(grpc_client._grpc().Export(pb.ExportRequest(map="big"), timeout=60))
    assert [len(c.probability) for c in chunks][:-1] == [65_536] * (len(chunks) - 1) and len(chunks) >= 2
    e = grpc_client.export("big")
    assert len(e.cell) == cells == len(np.unique(e.cell, axis=0))
    order = np.lexsort((e.cell[:, 2], e.cell[:, 1], e.cell[:, 0]))
    assert np.array_equal(order, np.arange(len(order)))
    rng = np.random.default_rng(3)
    q = (rng.uniform(-6.0, 6.0, (25_000, 3)) * [1.0, 1.0, 0.2]).astype(np.float32)
    assert_points_equal(grpc_client.query_points("big", q), http_client.query_points("big", q))


def test_reflection_v1_and_v1alpha(server: Server) -> None:
    """Both reflection services list the map service (raw protobuf: list_services = "")."""
    with grpc.insecure_channel(server.grpc_address) as channel:
        for version in ("v1", "v1alpha"):
            call = channel.stream_stream(
                f"/grpc.reflection.{version}.ServerReflection/ServerReflectionInfo",
                request_serializer=lambda b: b,
                response_deserializer=lambda b: b,
            )
            answers = list(call(iter([b"\x3a\x00"]), timeout=30))  # field 7 list_services: ""
            assert len(answers) == 1
            assert b"bgkmap.v1.MapService" in answers[0] and b"grpc.health.v1.Health" in answers[0]


def test_malformed_protobuf_is_invalid_argument(filled: Dict[str, Any], server: Server, grpc_client: Client) -> None:
    """Bytes that are not a protobuf message get INVALID_ARGUMENT and change nothing."""
    name = "wall_g"
    before = grpc_client.get_map(name)["version"]
    with grpc.insecure_channel(server.grpc_address) as channel:
        for method in ("InsertScan", "QueryPoints"):
            call = channel.unary_unary(
                f"/bgkmap.v1.MapService/{method}",
                request_serializer=lambda b: b,
                response_deserializer=lambda b: b,
            )
            with pytest.raises(grpc.RpcError) as err:
                call(b"\x0a\xff\xff\xff\xff\x0f", timeout=30)  # field 1 with a length past the end
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT, err.value
            assert "malformed protobuf" in (err.value.details() or "")
    assert grpc_client.get_map(name)["version"] == before


def test_non_finite_points_are_dropped_alike(grpc_client: Client, http_client: Client) -> None:
    pts = wall_and_floor(0.1)
    pts[::10, 1] = np.nan
    pts[5, 2] = np.inf
    expected_drop = int((~np.isfinite(pts).all(axis=1)).sum())
    grpc_client.create_map("nan_g")
    grpc_client.create_map("nan_h")
    a = grpc_client.insert_scan("nan_g", pts, ([0.0, 0.0, 0.5], IDENTITY), "s", 1)
    b = http_client.insert_scan("nan_h", pts, ([0.0, 0.0, 0.5], IDENTITY), "s", 1)
    assert a == b == {"applied": True, "version": 1, "dropped_points": expected_drop}
    q = query_grid()
    assert_points_equal(grpc_client.query_points("nan_g", q), http_client.query_points("nan_h", q))


def test_bad_requests_raise_bgkmap_error(filled: Dict[str, Any], grpc_client: Client, http_client: Client) -> None:
    pts = wall_and_floor(0.2)
    info = grpc_client.get_map("wall_g")
    for c in (grpc_client, http_client):
        for pose in [
            ([math.nan, 0.0, 0.5], IDENTITY),  # NaN translation
            ([0.0, 0.0, 0.5], [math.nan, 0.0, 0.0, 0.0]),  # NaN rotation
            ([0.0, 0.0, 0.5], [1.0, 1.0, 0.0, 0.0]),  # not a unit quaternion
        ]:
            with pytest.raises(BgkmapError) as e:
                c.insert_scan("wall_g", pts, pose, "bad", 1)
            assert e.value.code == "INVALID_ARGUMENT", (c.transport, pose, e.value)
            assert e.value.http_status == 400
            assert e.value.transport == c.transport
            assert e.value.message
        with pytest.raises(BgkmapError) as e:
            c.insert_scan("no-such-map", pts, ([0.0, 0.0, 0.5], IDENTITY), "s", 1)
        assert (e.value.code, e.value.http_status) == ("NOT_FOUND", 404)
        with pytest.raises(BgkmapError) as e:
            c.query_points("wall_g", query_grid()[:3], p_free=0.9, p_occ=0.1)
        assert e.value.code == "INVALID_ARGUMENT" and ("p_free" in e.value.message or "p_occ" in e.value.message), e.value
        with pytest.raises(BgkmapError) as e:
            c.query_box("wall_g", [1.0, 1.0, 1.0], [0.0, 0.0, 0.0])
        assert e.value.code == "INVALID_ARGUMENT", e.value
        with pytest.raises(BgkmapError) as e:
            c.cast_rays("wall_g", [0.0, 0.0, 0.5], [0.0, 0.0, 0.0], 5.0)
        assert e.value.code == "INVALID_ARGUMENT", e.value
        with pytest.raises(ValueError):
            c.query_points("wall_g", np.zeros((4, 2)))
    assert grpc_client.get_map("wall_g")["version"] == info["version"]


def test_unreachable_server_is_unavailable() -> None:
    for t in ("grpc", "http"):
        with Client("127.0.0.1:1", http_address="127.0.0.1:1", transport=t, timeout=5) as c:  # type: ignore[arg-type]
            with pytest.raises(BgkmapError) as e:
                c.list_maps()
            assert e.value.code == "UNAVAILABLE" and e.value.transport == t


# ---------------------------------------------------------------------------------------------
# Other clients against the same server.


def test_grpcurl_lists_service(server: Server) -> None:
    grpcurl = require_tool("grpcurl")
    out = subprocess.run(
        [grpcurl, "-plaintext", server.grpc_address, "list"], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    services = out.stdout.split()
    assert "bgkmap.v1.MapService" in services, out.stdout
    assert "grpc.health.v1.Health" in services, out.stdout
    out = subprocess.run(
        [grpcurl, "-plaintext", server.grpc_address, "list", "bgkmap.v1.MapService"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert "bgkmap.v1.MapService.QueryPoints" in out.stdout.split()
    health = subprocess.run(
        [grpcurl, "-plaintext", "-d", '{"service": "bgkmap.v1.MapService"}', server.grpc_address,
         "grpc.health.v1.Health/Check"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert health.returncode == 0, health.stderr
    assert json.loads(health.stdout)["status"] == "SERVING"


def test_grpcurl_query_points_matches_client(filled: Dict[str, Any], server: Server, grpc_client: Client) -> None:
    grpcurl = require_tool("grpcurl")
    q = query_grid()[:200]
    body = json.dumps({"map": "wall_g", "xyz_f32": base64.b64encode(q.astype("<f4").tobytes()).decode()})
    out = subprocess.run(
        [grpcurl, "-plaintext", "-d", body, server.grpc_address, "bgkmap.v1.MapService/QueryPoints"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    answer = json.loads(out.stdout)
    ref = grpc_client.query_points("wall_g", q)
    assert np.array_equal(np.array(answer["probability"], dtype=np.float64), ref.probability)
    assert np.array_equal(np.array(answer["variance"], dtype=np.float64), ref.variance)
    states = [{"CELL_STATE_UNKNOWN": 0, "CELL_STATE_FREE": 1, "CELL_STATE_OCCUPIED": 2}[s] for s in answer["state"]]
    assert np.array_equal(np.array(states, dtype=np.int8), ref.state)
    assert np.array_equal(np.array(answer["cell"], dtype=np.int32).reshape(-1, 3), ref.cell)
    assert int(answer["version"]) == ref.version
    # A malformed request: grpcurl shows the server's INVALID_ARGUMENT.
    bad = json.dumps({"map": "wall_g", "xyz_f32": base64.b64encode(b"\0" * 13).decode()})
    out = subprocess.run(
        [grpcurl, "-plaintext", "-d", bad, server.grpc_address, "bgkmap.v1.MapService/QueryPoints"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode != 0
    assert "InvalidArgument" in out.stderr and "xyz_f32" in out.stderr, out.stderr


def write_pcd(path: Path, points: np.ndarray, viewpoint: List[float]) -> None:
    """An ASCII PCD with x y z float fields and the sensor pose as VIEWPOINT."""
    header = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS x y z",
        "SIZE 4 4 4",
        "TYPE F F F",
        "COUNT 1 1 1",
        f"WIDTH {len(points)}",
        "HEIGHT 1",
        "VIEWPOINT " + " ".join(repr(float(v)) for v in viewpoint),
        f"POINTS {len(points)}",
        "DATA ascii",
    ]
    rows = [" ".join(repr(float(v)) for v in p) for p in points.astype(np.float32)]
    path.write_text("\n".join(header + rows) + "\n")


def test_curl_pcd_upload_and_query(server: Server, grpc_client: Client, http_client: Client, tmp_path: Path) -> None:
    curl = require_tool("curl")
    base = f"http://{server.http_address}"
    pts = wall_and_floor()
    origin = [0.0, 0.25, 0.5]  # float32-exact: VIEWPOINT is read as float32
    pcd = tmp_path / "scan.pcd"
    write_pcd(pcd, pts, origin + IDENTITY)

    def run_curl(*args: str) -> Dict[str, Any]:
        out = subprocess.run(
            [curl, "--silent", "--show-error", "--fail-with-body", "--noproxy", "*", *args],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert out.returncode == 0, (out.stdout, out.stderr)
        return json.loads(out.stdout)

    created = run_curl("-X", "PUT", "-H", "Content-Type: application/json", "--data", '{"max_range": 8}',
                       f"{base}/v1/maps/pcd")
    assert created["map"] == "pcd" and created["params"]["max_range"] == 8
    # A map's parameters as GET shows them are a valid PUT body (sub_cells a whole number).
    assert created["params"]["sub_cells"] == 8 and isinstance(created["params"]["sub_cells"], int)
    body = {k: v for k, v in created["params"].items() if k != "origin_as_free"}
    copy = run_curl("-X", "PUT", "-H", "Content-Type: application/json", "--data", json.dumps(body),
                    f"{base}/v1/maps/pcd_copy")
    assert copy["params"] == created["params"]
    # wait_applied=true: answered once integrated (read-your-writes), so version counts it.
    url = f"{base}/v1/maps/pcd/scans?source=c&seq=1&wait_applied=true"
    ack = run_curl("--data-binary", f"@{pcd}", "-H", "Content-Type: application/x-pcd", url)
    assert ack == {"applied": True, "version": 1, "dropped_points": 0}
    again = run_curl("--data-binary", f"@{pcd}", "-H", "Content-Type: application/x-pcd", url)
    assert again == {"applied": False, "version": 1, "dropped_points": 0}

    # The same scan through the client (gRPC, and the client's own PCD upload) gives the same map.
    grpc_client.create_map("pcd_ref", max_range=8)
    grpc_client.insert_scan("pcd_ref", pts, (origin, IDENTITY), "c", 1)
    grpc_client.create_map("pcd_client", max_range=8)
    assert http_client.insert_pcd("pcd_client", pcd, "c", 1)["applied"] is True

    q = query_grid()[:300]
    body = json.dumps({"points": q.astype(np.float64).tolist()})
    answer = run_curl("-H", "Content-Type: application/json", "--data", body, f"{base}/v1/maps/pcd/query/points")
    ref = grpc_client.query_points("pcd_ref", q)
    res = answer["results"]
    assert answer["version"] == 1
    assert np.array_equal(np.array([r["probability"] for r in res]), ref.probability)
    assert np.array_equal(np.array([r["variance"] for r in res]), ref.variance)
    assert [r["state"] for r in res] == list(state_names(ref.state))
    assert np.array_equal(np.array([r["cell"] for r in res], dtype=np.int32), ref.cell)
    assert_points_equal(ref, grpc_client.query_points("pcd_client", q))
    assert ref.probability[0] > 0.5 and ref.state[1] == FREE  # one scan: the wall is barely evidenced

    # Errors come back as JSON {"error": …} with a 4xx status.
    out = subprocess.run(
        [curl, "--silent", "--noproxy", "*", "-o", "-", "-w", "\n%{http_code}", "--data-binary", f"@{pcd}",
         "-H", "Content-Type: application/x-pcd", f"{base}/v1/maps/pcd/scans?source=c"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    body_text, status = out.stdout.rsplit("\n", 1)
    assert status == "400" and "seq" in json.loads(body_text)["error"]


def test_exact_operations_over_both_transports(grpc_client: Client, http_client: Client) -> None:
    """Re-posing the sensor-frame scan and retracting its source give the maps built without
    them; merging a map that shares every scan changes nothing; over gRPC and HTTP alike."""
    s = scans()
    lidar = [x for x in s if x["source"] == "lidar"]
    cam = next(x for x in s if x["source"] == "cam")
    corrected = ([0.15, -0.25, 0.7], yaw(math.radians(27)))
    q = query_grid()
    for c, tag in ((grpc_client, "g"), (http_client, "h")):
        full, reposed, clean = (f"ops_{tag}_{n}" for n in ("full", "reposed", "clean"))
        for name in (full, reposed, clean):
            c.create_map(name, max_range=MAX_RANGE)
        for x in s:
            assert c.insert_scan(full, wait_applied=False, **x)["applied"]
        for x in lidar:
            c.insert_scan(clean, **x)
            c.insert_scan(reposed, **x)
        c.insert_scan(reposed, **dict(cam, pose=corrected))
        r = c.repose_scans(full, [("cam", 7, corrected)])
        assert (r["scans"], r["version"]) == (1, 5)
        assert_points_equal(c.query_points(full, q), c.query_points(reposed, q))
        r = c.retract_scans(full, source="cam")
        assert (r["scans"], r["version"]) == (1, 6)
        assert_points_equal(c.query_points(full, q), c.query_points(clean, q))
        info = c.get_map(full)
        assert info["scans"] == 3 and info["sources"]["cam"]["retracted"] == 1
        r = c.merge_map(full, from_map=clean)
        assert (r["scans"], r["shared_scans"]) == (0, 3)
        assert_points_equal(c.query_points(full, q), c.query_points(clean, q))
        with pytest.raises(BgkmapError) as e:
            c.retract_scans(full, scans=[("cam", 7)])
        assert (e.value.code, e.value.http_status) in (("NOT_FOUND", None), ("NOT_FOUND", 404)), e.value


def test_restart_keeps_maps(tmp_path: Path) -> None:
    """A map survives SIGTERM (exit 0) and a restart on the same data directory, bit for bit."""
    data = tmp_path / "data"
    s = start_server(data)
    try:
        with s.client("grpc") as c:
            c.create_map("keep", max_range=MAX_RANGE)
            for scan in scans()[:2]:
                c.insert_scan("keep", **scan)
            before = c.query_points("keep", query_grid())
            info = c.get_map("keep")
    finally:
        code = s.stop()
    assert code == 0, s.stderr()
    s = start_server(data)
    try:
        with s.client("http") as c:
            assert_points_equal(before, c.query_points("keep", query_grid()))
            again = c.get_map("keep")
            assert again["version"] == info["version"] == 2
            assert again["cells_with_evidence"] == info["cells_with_evidence"]
            assert c.insert_scan("keep", **scans()[0])["applied"] is False  # dedup survives too
    finally:
        code = s.stop()
    assert code == 0, s.stderr()
