"""Errors the client raises for gRPC failures: one class per status code the server documents.

Every class derives from `PntrError`, which carries the status code's name (`code`, e.g.
"UNAUTHENTICATED") and the server's message (`details`). Mistakes in the caller's own arguments are
found before anything is sent and raised as `ValueError` instead.
"""

from __future__ import annotations

import grpc


class PntrError(Exception):
    """A gRPC call to pntr-server failed.

    Attributes:
        code: the gRPC status code's name, e.g. "UNAUTHENTICATED", "INVALID_ARGUMENT".
        details: the server's (or the transport's) message.
        operation: the RPC that failed ("Localize", "LocalizeStream", "GetMapInfo").
    """

    def __init__(self, code: str, details: str, operation: str = "") -> None:
        self.code = code
        self.details = details
        self.operation = operation
        prefix = f"{operation}: " if operation else ""
        super().__init__(f"{prefix}{code}: {details}")


class InvalidArgumentError(PntrError):
    """INVALID_ARGUMENT: the server could not read or use the frame (the details say which field)."""


class NotFoundError(PntrError):
    """NOT_FOUND: the server holds no map with that map_id."""


class ResourceExhaustedError(PntrError):
    """RESOURCE_EXHAUSTED: the server's queue is full; retry later, with back-off."""


class DeadlineExceededError(PntrError):
    """DEADLINE_EXCEEDED: no answer before the call's deadline (`timeout_s`)."""


class UnauthenticatedError(PntrError):
    """UNAUTHENTICATED: the server wants a bearer token and the one sent is missing or wrong."""


class UnavailableError(PntrError):
    """UNAVAILABLE: the server cannot be reached, is still loading its maps, or is shutting down."""


class OutOfRangeError(PntrError):
    """OUT_OF_RANGE: the request is larger than the server's maximum message size."""


class CancelledError(PntrError):
    """CANCELLED: the call was cancelled (by the caller, or a deadline passed mid-transfer)."""


_BY_CODE: dict[str, type[PntrError]] = {
    "INVALID_ARGUMENT": InvalidArgumentError,
    "NOT_FOUND": NotFoundError,
    "RESOURCE_EXHAUSTED": ResourceExhaustedError,
    "DEADLINE_EXCEEDED": DeadlineExceededError,
    "UNAUTHENTICATED": UnauthenticatedError,
    "UNAVAILABLE": UnavailableError,
    "OUT_OF_RANGE": OutOfRangeError,
    "CANCELLED": CancelledError,
}


def error_from_rpc(e: grpc.RpcError, operation: str) -> PntrError:
    """The `PntrError` subclass for a failed call (`e` is the `grpc.RpcError` the stub raised)."""
    code_fn = getattr(e, "code", None)
    details_fn = getattr(e, "details", None)
    code = code_fn() if callable(code_fn) else None
    name = code.name if isinstance(code, grpc.StatusCode) else "UNKNOWN"
    details = (details_fn() if callable(details_fn) else None) or str(e)
    return _BY_CODE.get(name, PntrError)(name, details, operation)
