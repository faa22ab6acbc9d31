"""The two transports under every call: a lazily opened gRPC channel and a urllib opener for
the HTTP port, each turning the server's refusals into :class:`BgkmapError` with the same
status names. Knows nothing of the map calls themselves."""

from __future__ import annotations

import ipaddress
import json
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Literal, Mapping, Optional

import grpc

from ._pb import bgkmap_pb2_grpc as pb_grpc
from ._types import BgkmapError

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


class _Transport:
    """The connection state of a :class:`~bgkmap_client.Client` (see its docstring for the
    arguments) and the plumbing its calls share."""

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
