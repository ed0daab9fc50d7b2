"""`Client`: a connection to pntr-server and its three calls (Localize, LocalizeStream, GetMapInfo)."""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import numpy.typing as npt

from pntr_client._messages import (
    answer_from_response,
    as_frame,
    continuation_message,
    frame_convention_value,
    make_request,
    map_info_from_message,
)
from pntr_client._proto import localizer_pb2 as pb2
from pntr_client._proto import localizer_pb2_grpc as pb2_grpc
from pntr_client._values import Answer, Continuation, Frame, MapInfo, Prior
from pntr_client.errors import error_from_rpc

# Large enough for a 4K RGB-D frame sent raw (3840 x 2160 x (3 + 4) bytes is about 58 MiB).
MAX_MESSAGE_BYTES = 64 << 20
_RETRYABLE = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED)

PathOrPem = str | os.PathLike[str] | bytes


class Client:
    """A connection to a pntr-server.

    Args:
        addr: the server, "HOST:PORT".
        token: bearer token, sent as `authorization: Bearer <token>` metadata with every call
            (for a server started with a token); None sends none.
        tls_ca: connect with TLS, trusting the CA certificate(s) in this PEM file (a path) or these PEM
            bytes (the server's own certificate when it is self-signed); None connects in plaintext.
        tls_server_name: the name to check in the server certificate when it differs from the host
            in `addr` (e.g. connecting by IP address).
        timeout_s: default deadline of `localize` and `map_info` calls, seconds; None for none.
        frame_convention: the convention of answers (and priors) for every call that does not name
            one: "map" (the map's own frame and camera axes), "ros" (REP 103 z-up map frame, optical
            camera axes x right, y down, z forward: `Answer.pose` is map_from_camera_optical), or None
            for the server's default (`MapInfo.frame_convention`).

    Connecting is lazy: constructing a Client never fails for an unreachable server; the first call
    does (`UnavailableError`). Use `map_info(wait_s=...)` to wait for a server that is starting.
    Close it with `close()`, or use it as a context manager. gRPC failures raise `PntrError`
    subclasses (`pntr_client.errors`); mistakes in the arguments raise ValueError before sending,
    and an unreadable `tls_ca` file raises OSError here. A Client may be shared between threads.
    """

    def __init__(
        self,
        addr: str,
        token: str | None = None,
        tls_ca: PathOrPem | None = None,
        *,
        tls_server_name: str | None = None,
        timeout_s: float | None = 60.0,
        frame_convention: str | None = None,
    ) -> None:
        if not isinstance(addr, str) or not addr:
            raise ValueError(f"addr must be 'HOST:PORT', got {addr!r}")
        if token is not None and (not isinstance(token, str) or any(c in token for c in "\r\n")):
            raise ValueError("token must be a string without line breaks (strip the one read from a file)")
        if timeout_s is not None and not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0 seconds or None, got {timeout_s}")
        if frame_convention is not None:
            frame_convention_value(frame_convention)  # ValueError now rather than at the first call
        self._frame_convention = frame_convention
        self._addr = addr
        self._timeout_s = timeout_s
        self._metadata: tuple[tuple[str, str], ...] | None = (("authorization", f"Bearer {token}"),) if token else None
        options: list[tuple[str, Any]] = [
            ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
            ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
        ]
        if tls_ca is None:
            self._channel = grpc.insecure_channel(addr, options=options)
        else:
            ca = tls_ca if isinstance(tls_ca, bytes) else Path(os.fspath(tls_ca)).read_bytes()
            if tls_server_name:
                options.append(("grpc.ssl_target_name_override", tls_server_name))
            creds = grpc.ssl_channel_credentials(root_certificates=ca)
            self._channel = grpc.secure_channel(addr, creds, options=options)
        stub_class: Any = pb2_grpc.LocalizerStub  # generated code, untyped
        self._stub = stub_class(self._channel)

    @property
    def addr(self) -> str:
        """The server address this client connects to."""
        return self._addr

    def close(self) -> None:
        """Close the channel; calls in flight are cancelled."""
        self._channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Client({self._addr!r})"

    def _timeout(self, timeout_s: float | None) -> float | None:
        return self._timeout_s if timeout_s is None else timeout_s

    def _call_metadata(self, map_id: str) -> tuple[tuple[str, str], ...] | None:
        # The map id also travels as metadata, so a proxy can route by map without reading the body.
        extra = (("x-pntr-map-id", map_id),) if map_id else ()
        return (self._metadata or ()) + extra or None

    def localize(
        self,
        rgb: npt.NDArray[np.uint8],
        depth: npt.NDArray[np.floating[Any]] | npt.NDArray[np.uint16],
        intrinsics: Sequence[float] | None = None,
        map_id: str = "",
        prior: Prior | None = None,
        *,
        request_id: str = "",
        timeout_s: float | None = None,
        frame_convention: str | None = None,
    ) -> Answer:
        """Localize one RGB-D frame.

        Args:
            rgb: HxWx3 uint8 colour image, R G B order (OpenCV's BGR needs rgb = bgr[..., ::-1]).
            depth: HxW planar depth (along the optical axis), pixel-aligned with rgb and of its
                size: float metres (float32; other float dtypes are converted), where 0, negative,
                NaN or infinite pixels are missing depth; or uint16 millimetres (a RealSense or ROS
                16UC1 image), sent as is, where 0 is missing depth. Other dtypes are refused, and so
                are values implausible for their unit (a median outside 0.05 .. 50 m: float
                millimetres, metres in uint16).
            intrinsics: (fx, fy, cx, cy) in pixels (OpenCV convention), optionally followed by 4 or 5
                plumb_bob distortion coefficients (k1, k2, p1, p2[, k3]); None means the HPointLoc
                camera (fx = fy = 128, cx = cy = 127.5), accepted for 256x256 frames only.
            map_id: the map to localize in; "" means the server's only map.
            prior: where the camera roughly is (`Prior`), or None for a global search.
            request_id: optional id echoed in the answer and logged by the server.
            timeout_s: deadline of this call, seconds [the client's `timeout_s`].
            frame_convention: "map" or "ros" for this call's answer and prior [the client's].

        Returns:
            The `Answer` (LOCALIZED with a pose, or NOT_LOCALIZED with a reason).

        Raises:
            ValueError: an input is malformed (the message names it) - nothing was sent.
            PntrError: the call failed (e.g. `UnauthenticatedError`, `InvalidArgumentError`).
        """
        req = make_request(
            rgb, depth, intrinsics, map_id, prior, request_id, frame_convention=frame_convention or self._frame_convention
        )
        try:
            resp = self._stub.Localize(req, metadata=self._call_metadata(map_id), timeout=self._timeout(timeout_s))
        except grpc.RpcError as e:
            raise error_from_rpc(e, "Localize") from e
        return answer_from_response(resp)

    def localize_stream(
        self,
        frames: Iterable[Frame | Mapping[str, Any]],
        map_id: str = "",
        *,
        timeout_s: float | None = None,
        frame_convention: str | None = None,
        continuation: Continuation | None = None,
    ) -> Iterator[Answer]:
        """Localize a stream of frames over one LocalizeStream call; yields one `Answer` per frame, in
        the order sent (the server may use the stream's last verified pose: `Answer.mode` TRACKING).

        Args:
            frames: `Frame`s, or dicts with the same keys (rgb, depth, intrinsics, prior,
                request_id, relocalize, stamp_s, odometry), consumed lazily as the server takes them: a generator
                reading a camera works. A frame with `relocalize=True` is searched over the whole
                map whatever the stream's state (after the robot was carried elsewhere).
            map_id: the map to localize every frame in; "" means the server's only map.
            timeout_s: deadline of the whole stream, seconds; None (default) for none.
            frame_convention: "map" or "ros" for every frame's answer and prior [the client's].
            continuation: where an earlier stream left the camera (`Answer.as_continuation` of its
                last LOCALIZED answer), sent with the first frame: re-opening a stream after a
                server restart or a dropped connection then continues its track, and the first
                frame's map fix is held to the camera's motion since (a look-alike is refused as
                it would have been). Ignored when the first frame has `relocalize=True`.

        Raises:
            ValueError: a frame is malformed (the message names the frame's index); raised after the
                answers to the frames before it, and the stream is closed.
            PntrError: the stream failed (the error ends it, as the server documents).
        """
        failure: list[BaseException] = []
        convention = frame_convention or self._frame_convention
        if convention is not None:
            frame_convention_value(convention)
        if continuation is not None and not isinstance(continuation, Continuation):
            raise ValueError(
                "continuation must be a pntr_client.Continuation(pose, stamp_s=None, sigma_m=0.0), got "
                f"{type(continuation).__name__} (an Answer becomes one with answer.as_continuation(stamp_s))"
            )

        def requests() -> Iterator[pb2.LocalizeRequest]:
            # Runs in gRPC's sending thread: an exception here would only cancel the call, so keep it
            # for the caller's thread and end the stream cleanly instead.
            try:
                for i, item in enumerate(frames):
                    f = as_frame(item, i)
                    req = make_request(
                        f.rgb,
                        f.depth,
                        f.intrinsics,
                        map_id,
                        f.prior,
                        f.request_id,
                        frame_convention=convention,
                        relocalize=f.relocalize,
                        stamp_s=f.stamp_s,
                        odometry=f.odometry,
                        where=f"frame {i}: ",
                    )
                    if i == 0 and continuation is not None:
                        req.continuation.CopyFrom(continuation_message(continuation))
                    yield req
            except Exception as e:  # noqa: BLE001 - re-raised in the caller's thread below
                failure.append(e)

        call = self._stub.LocalizeStream(requests(), metadata=self._call_metadata(map_id), timeout=timeout_s)
        try:
            for resp in call:
                yield answer_from_response(resp)
        except grpc.RpcError as e:
            if failure:
                raise failure[0] from None
            raise error_from_rpc(e, "LocalizeStream") from e
        finally:
            call.cancel()  # no-op when finished; stops the call when the caller stops iterating
        if failure:
            raise failure[0]

    def map_info(self, map_id: str = "", *, wait_s: float = 0.0) -> MapInfo:
        """Describe a loaded map ("" = the server's only map).

        Args:
            map_id: the map to describe.
            wait_s: keep retrying for up to this many seconds while the server is unreachable or still
                loading (UNAVAILABLE, DEADLINE_EXCEEDED); 0 tries once with the client's timeout.

        Raises:
            PntrError: e.g. `UnavailableError` (unreachable), `NotFoundError` (no such map),
                `DeadlineExceededError` (no answer within `wait_s`).
        """
        req = pb2.GetMapInfoRequest(map_id=map_id)
        end = time.monotonic() + wait_s
        while True:
            timeout = max(0.5, end - time.monotonic()) if wait_s > 0 else self._timeout_s
            try:
                msg = self._stub.GetMapInfo(req, metadata=self._call_metadata(map_id), timeout=timeout)
                return map_info_from_message(msg)
            except grpc.RpcError as e:
                if wait_s <= 0 or e.code() not in _RETRYABLE or time.monotonic() + 0.25 >= end:
                    raise error_from_rpc(e, "GetMapInfo") from e
            time.sleep(0.25)
