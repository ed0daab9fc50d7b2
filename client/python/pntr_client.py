#!/usr/bin/env python3
"""Localize HPointLoc query frames against a running pntr-server and report the error of each pose.

The gRPC stubs are generated from proto/pntr/v1/localizer.proto with grpcio-tools the first time
they are needed, into a cache folder keyed by the proto's content and the tool versions (nothing
generated is committed). See README.md beside this file.

Usage:
  python pntr_client.py --addr HOST:PORT --dataset DIR --scene NAME [--point N] [--queries K]
                        [--token T | --token-file F] [--tls-ca PEM] [--json]

Exit status: 0 when every query was answered (LOCALIZED or NOT_LOCALIZED), 1 when the server could
not be reached or answered an RPC with an error, 2 for bad arguments or unreadable input files.

The functions `load_stubs`, `open_channel`, `make_request` and `read_point` can also be imported and
used from other Python code (e.g. a ROS node).
"""

import argparse
import hashlib
import importlib
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

# HPointLoc stores depth as metres / 10 in 0..1; 0 and >= 1.0 (the far clip) are not measurements.
HPOINTLOC_DEPTH_SCALE_M = 10.0
DATASET_DIR = "HPointLoc_dataset"
DEFAULT_PROTO_ROOT = Path(__file__).resolve().parent.parent.parent / "proto"
PROTO_FILE = "pntr/v1/localizer.proto"
# (metres, degrees) thresholds of the evaluation protocol (same as `pntr eval`).
THRESHOLDS = [(5.0, 20.0), (1.0, 10.0), (0.5, 5.0), (0.25, 2.0)]
MAX_MESSAGE_BYTES = 64 << 20


class ClientError(Exception):
    """An error to report in one line, with the exit status to end with."""

    def __init__(self, message, exit_code=1):
        super().__init__(message)
        self.exit_code = exit_code


# --- stubs -------------------------------------------------------------------------------------


def _cache_root():
    explicit = os.environ.get("PNTR_CLIENT_CACHE")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(xdg) / "pntr" / "python-stubs"


def load_stubs(proto_root=None):
    """Generate (once, cached) and import the stubs; returns (localizer_pb2, localizer_pb2_grpc)."""
    try:
        import grpc  # noqa: F401  (checked here so the error names the missing package)
        from google import protobuf
        from grpc_tools import protoc
    except ImportError as e:
        raise ClientError(f"{e}: install the client's requirements "
                          f"(pip install -r client/python/requirements.txt)", 2) from e
    proto_root = Path(proto_root or os.environ.get("PNTR_PROTO_DIR") or DEFAULT_PROTO_ROOT)
    proto = proto_root / PROTO_FILE
    if not proto.is_file():
        raise ClientError(f"proto file not found: {proto} (pass --proto DIR, the folder holding "
                          f"{PROTO_FILE})", 2)
    tools_version = _dist_version("grpcio-tools")
    key = hashlib.sha256(proto.read_bytes() + f"|{tools_version}|{protobuf.__version__}".encode())
    root = _cache_root()
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError:
        root = Path(tempfile.gettempdir()) / f"pntr-python-stubs-{os.getuid()}"
        root.mkdir(parents=True, exist_ok=True)
    out = root / key.hexdigest()[:20]
    if not (out / "pntr" / "v1" / "localizer_pb2_grpc.py").is_file():
        tmp = Path(tempfile.mkdtemp(prefix=".gen-", dir=root))
        try:
            include = Path(protoc.__file__).parent / "_proto"  # google/protobuf/*.proto
            rc = protoc.main(["grpc_tools.protoc", f"-I{proto_root}", f"-I{include}",
                              f"--python_out={tmp}", f"--grpc_python_out={tmp}", PROTO_FILE])
            if rc != 0:
                raise ClientError(f"grpc_tools.protoc failed on {proto} (exit {rc})", 2)
            try:
                os.rename(tmp, out)  # atomic: concurrent clients never see half a folder
            except OSError:
                if not out.is_dir():
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    if str(out) not in sys.path:
        sys.path.insert(0, str(out))
    pb2 = importlib.import_module("pntr.v1.localizer_pb2")
    pb2_grpc = importlib.import_module("pntr.v1.localizer_pb2_grpc")
    return pb2, pb2_grpc


def _dist_version(name):
    from importlib import metadata
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "unknown"


# --- dataset -----------------------------------------------------------------------------------


def decode_depth(normalised):
    """HPointLoc normalised depth -> float32 metres, 0 where invalid (as pntr's Rust reader does)."""
    import numpy as np
    v = np.asarray(normalised, dtype=np.float32)
    if v.ndim == 3 and v.shape[-1] == 1:
        v = v[..., 0]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(v) & (v > 0.0) & (v < 1.0)
    return np.where(valid, v * np.float32(HPOINTLOC_DEPTH_SCALE_M), np.float32(0.0)).astype(np.float32)


def point_files(dataset, scene, point=None):
    """[(index, path)] of the scene's Point files, sorted by index (one when `point` is given)."""
    root = Path(dataset)
    if not root.exists():
        raise ClientError(f"dataset folder not found: {root}", 2)
    sdir = root / DATASET_DIR / scene
    if root.name == DATASET_DIR:
        sdir = root / scene
    if not sdir.is_dir():
        raise ClientError(f"scene folder not found: {sdir} (expected "
                          f"<dataset>/{DATASET_DIR}/<scene>/<scene>_point<N>.hdf5)", 2)
    if point is not None:
        p = sdir / f"{scene}_point{point}.hdf5"
        if not p.is_file():
            raise ClientError(f"Point file not found: {p}", 2)
        return [(point, p)]
    files = []
    for p in sdir.glob(f"{scene}_point*.hdf5"):
        idx = p.name[len(scene) + len("_point"):-len(".hdf5")]
        if idx.isdigit():
            files.append((int(idx), p))
    if not files:
        raise ClientError(f"no Point files ({scene}_point<N>.hdf5) in {sdir}", 2)
    return sorted(files)


def read_point(path, limit=None):
    """Yield (i, rgb HxWx3 uint8, depth HxW float32 metres, gps (3,), quat wxyz (4,)) per query."""
    import h5py
    import numpy as np
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ClientError(f"cannot open {path}: {e}", 2) from e
    with f:
        for field in ("rgb", "depth", "gps", "quat"):
            if field not in f:
                raise ClientError(f"{path}: field `{field}` missing (not an HPointLoc Point file?)", 2)
        rgb, depth = f["rgb"], f["depth"]
        n = rgb.shape[0]
        if rgb.ndim != 4 or rgb.shape[3] != 3 or rgb.dtype != np.uint8:
            raise ClientError(f"{path}: `rgb` is {rgb.dtype}{rgb.shape}, expected uint8 (N, H, W, 3)", 2)
        if depth.shape[:3] != rgb.shape[:3]:
            raise ClientError(f"{path}: `depth` shape {depth.shape} does not match `rgb` {rgb.shape}", 2)
        gps = np.asarray(f["gps"][:], dtype=np.float64)
        quat = np.asarray(f["quat"][:], dtype=np.float64)
        if gps.shape != (n, 3) or quat.shape != (n, 4):
            raise ClientError(f"{path}: gps {gps.shape} / quat {quat.shape}, expected ({n}, 3) / ({n}, 4)", 2)
        for i in range(n if limit is None else min(n, limit)):
            yield i, np.ascontiguousarray(rgb[i]), decode_depth(depth[i]), gps[i], quat[i]


# --- gRPC --------------------------------------------------------------------------------------


def open_channel(addr, tls_ca=None, tls_server_name=None):
    """A channel to `addr` (HOST:PORT): plaintext, or TLS trusting the CA certificate(s) in `tls_ca`."""
    import grpc
    options = [("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
               ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES)]
    if tls_ca is None:
        return grpc.insecure_channel(addr, options=options)
    try:
        ca = Path(tls_ca).read_bytes()
    except OSError as e:
        raise ClientError(f"cannot read --tls-ca {tls_ca}: {e.strerror}", 2) from e
    if tls_server_name:
        options.append(("grpc.ssl_target_name_override", tls_server_name))
    return grpc.secure_channel(addr, grpc.ssl_channel_credentials(root_certificates=ca), options=options)


def make_request(pb2, rgb, depth_m, intrinsics=None, map_id="", request_id=""):
    """A LocalizeRequest from an HxWx3 uint8 RGB array and an HxW depth array in metres (0 = invalid).

    `intrinsics` is (fx, fy, cx, cy) or None (the server then uses the HPointLoc camera, 256 x 256).
    """
    import numpy as np
    h, w = rgb.shape[:2]
    req = pb2.LocalizeRequest(
        map_id=map_id,
        request_id=request_id,
        rgb=pb2.Image(width=w, height=h, encoding=pb2.RAW_RGB8,
                      data=np.ascontiguousarray(rgb, dtype=np.uint8).tobytes()),
        depth=pb2.Depth(width=w, height=h, encoding=pb2.FLOAT32_METERS,
                        data=np.ascontiguousarray(depth_m, dtype="<f4").tobytes()),
    )
    if intrinsics is not None:
        fx, fy, cx, cy = intrinsics
        req.intrinsics.CopyFrom(pb2.Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy))
    return req


def _rpc_error(e, addr, what):
    """A ClientError for a grpc.RpcError, with a hint for the common cases."""
    import grpc
    code, details = e.code(), e.details() or ""
    if code == grpc.StatusCode.UNAVAILABLE:
        return ClientError(f"cannot reach pntr-server at {addr} ({what}): UNAVAILABLE: {details}")
    if code == grpc.StatusCode.UNAUTHENTICATED:
        return ClientError(f"{what}: UNAUTHENTICATED: {details} (pass the server's token with --token, "
                           f"--token-file or PNTR_TOKEN)")
    return ClientError(f"{what}: {code.name}: {details}")


def server_info(stub, pb2, addr, metadata, map_id, connect_timeout):
    """GetMapInfo, retried while the server is unreachable or still loading, up to connect_timeout."""
    import grpc
    end = time.monotonic() + connect_timeout
    while True:
        try:
            return stub.GetMapInfo(pb2.GetMapInfoRequest(map_id=map_id), metadata=metadata,
                                   timeout=max(0.5, end - time.monotonic()))
        except grpc.RpcError as e:
            code = e.code()
            if code not in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                raise _rpc_error(e, addr, "GetMapInfo") from e
            if time.monotonic() + 0.25 >= end:
                if code == grpc.StatusCode.DEADLINE_EXCEEDED:
                    raise ClientError(f"cannot reach pntr-server at {addr}: no answer within "
                                      f"{connect_timeout:g} s") from e
                raise _rpc_error(e, addr, "GetMapInfo") from e
            time.sleep(0.25)


# --- errors ------------------------------------------------------------------------------------


def _quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def _normalised(q):
    n = math.sqrt(sum(c * c for c in q))
    return tuple(c / n for c in q)


def rotation_error_deg(q_a, q_b):
    """Geodesic angle between two rotations given as (w, x, y, z) quaternions, degrees in 0..180."""
    a, b = _normalised(q_a), _normalised(q_b)
    d = _quat_mul((a[0], -a[1], -a[2], -a[3]), b)
    return math.degrees(2.0 * math.atan2(math.sqrt(d[1] ** 2 + d[2] ** 2 + d[3] ** 2), abs(d[0])))


def translation_error_m(t_a, t_b):
    return math.sqrt(sum((x - y) ** 2 for x, y in zip(t_a, t_b)))


def _median(xs):
    xs = sorted(xs)
    if not xs:
        return None
    m = len(xs) // 2
    return xs[m] if len(xs) % 2 else 0.5 * (xs[m - 1] + xs[m])


def summarise(results):
    loc = [r for r in results if r["status"] == "LOCALIZED"]
    n = len(results)
    recall = {}
    for m, d in THRESHOLDS:
        hit = sum(1 for r in loc if r["translation_error_m"] <= m and r["rotation_error_deg"] <= d)
        recall[f"{m:g}m_{d:g}deg"] = hit / n if n else 0.0
    lat = [r["latency_ms"] for r in results]
    return {
        "queries": n,
        "localized": len(loc),
        "localized_share": len(loc) / n if n else 0.0,
        "median_translation_error_m": _median([r["translation_error_m"] for r in loc]),
        "median_rotation_error_deg": _median([r["rotation_error_deg"] for r in loc]),
        "recall": recall,
        "latency_ms": {"mean": sum(lat) / n if n else None, "median": _median(lat),
                       "max": max(lat) if lat else None},
    }


# --- command line ------------------------------------------------------------------------------


def parse_args(argv):
    p = argparse.ArgumentParser(
        description="Localize HPointLoc query frames with a running pntr-server; print pose and error.")
    p.add_argument("--addr", default="127.0.0.1:50051", help="server address HOST:PORT [%(default)s]")
    p.add_argument("--dataset", required=True,
                   help=f"dataset folder (the one holding {DATASET_DIR}/, or that folder itself)")
    p.add_argument("--scene", required=True, help="scene name (folder under HPointLoc_dataset)")
    p.add_argument("--point", type=int, help="only this Point index [all Points of the scene]")
    p.add_argument("--queries", type=int, metavar="K", help="at most the first K queries of each Point [all]")
    p.add_argument("--map-id", default="", help="map to localize in [the server's only map]")
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY",
                   help="camera intrinsics in pixels [omitted: the server's HPointLoc camera]")
    p.add_argument("--token", default=os.environ.get("PNTR_TOKEN"),
                   help="bearer token (sent as `authorization: Bearer <T>`) [$PNTR_TOKEN]")
    p.add_argument("--token-file", help="read the bearer token from this file")
    p.add_argument("--tls-ca", metavar="PEM", help="use TLS, trusting the CA certificate(s) in this file")
    p.add_argument("--tls-server-name", help="expect this name in the server certificate [host of --addr]")
    p.add_argument("--timeout", type=float, default=60.0, help="deadline of each Localize call, s [%(default)s]")
    p.add_argument("--connect-timeout", type=float, default=10.0,
                   help="how long to wait for the server to answer at all, s [%(default)s]")
    p.add_argument("--proto", help=f"folder holding {PROTO_FILE} [{DEFAULT_PROTO_ROOT}]")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of lines")
    args = p.parse_args(argv)
    if args.queries is not None and args.queries < 1:
        p.error("--queries must be at least 1")
    if args.intrinsics is not None:
        try:
            vals = [float(v) for v in args.intrinsics.split(",")]
            if len(vals) != 4:
                raise ValueError
        except ValueError:
            p.error("--intrinsics needs four numbers: FX,FY,CX,CY")
        args.intrinsics = tuple(vals)
    if args.token_file:
        try:
            args.token = Path(args.token_file).read_text().strip()
        except OSError as e:
            p.error(f"cannot read --token-file {args.token_file}: {e.strerror}")
    return args


def _fmt_err(r):
    if r["status"] != "LOCALIZED":
        return f"{r['status']}  ({r['reason']})"
    t, q = r["translation"], r["rotation_wxyz"]
    return (f"LOCALIZED  t=({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) "
            f"q=({q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f})  "
            f"err {r['translation_error_m']:.3f} m {r['rotation_error_deg']:.2f} deg  "
            f"conf {r['confidence']:.2f}  inliers {r['inliers']}  match {r['matched_image_id']}")


def run(args):
    files = point_files(args.dataset, args.scene, args.point)
    pb2, pb2_grpc = load_stubs(args.proto)
    import grpc
    metadata = [("authorization", f"Bearer {args.token}")] if args.token else None
    channel = open_channel(args.addr, args.tls_ca, args.tls_server_name)
    with channel:
        stub = pb2_grpc.LocalizerStub(channel)
        info = server_info(stub, pb2, args.addr, metadata, args.map_id, args.connect_timeout)
        if not args.json:
            print(f"server {args.addr}: map {info.map_id} ({info.images} images, {info.points} Points, "
                  f"preset {info.preset}, axes {info.camera_axes})")
        results = []
        for point, path in files:
            for i, rgb, depth, gps, quat in read_point(path, args.queries):
                qid = f"{args.scene}/point{point}/q{i}"
                req = make_request(pb2, rgb, depth, args.intrinsics, args.map_id, request_id=qid)
                t0 = time.perf_counter()
                try:
                    resp = stub.Localize(req, metadata=metadata, timeout=args.timeout)
                except grpc.RpcError as e:
                    raise _rpc_error(e, args.addr, f"Localize {qid}") from e
                ms = (time.perf_counter() - t0) * 1e3
                r = {"query": qid, "status": pb2.Status.Name(resp.status), "reason": resp.reason,
                     "confidence": resp.confidence, "inliers": resp.inliers,
                     "matched_image_id": resp.matched_image_id, "latency_ms": ms,
                     "server_ms": {t.stage: t.seconds * 1e3 for t in resp.timings},
                     "gt_translation": [float(v) for v in gps],
                     "gt_rotation_wxyz": [float(v) for v in quat]}
                if resp.status == pb2.LOCALIZED:
                    t = resp.pose.translation
                    q = resp.pose.rotation
                    r["translation"] = [t.x, t.y, t.z]
                    r["rotation_wxyz"] = [q.w, q.x, q.y, q.z]
                    r["translation_error_m"] = translation_error_m(r["translation"], gps)
                    r["rotation_error_deg"] = rotation_error_deg(r["rotation_wxyz"], quat)
                results.append(r)
                if not args.json:
                    print(f"{qid}  {_fmt_err(r)}  {ms:.0f} ms", flush=True)
    summary = summarise(results)
    if args.json:
        server = {"addr": args.addr, "map_id": info.map_id, "images": info.images, "points": info.points,
                  "preset": info.preset, "camera_axes": info.camera_axes}
        print(json.dumps({"server": server, "queries": results, "summary": summary}, indent=1))
    else:
        s = summary
        if not s["queries"]:
            print("summary: no queries")
            return
        line = f"summary: {s['localized']}/{s['queries']} LOCALIZED ({100 * s['localized_share']:.1f}%)"
        if s["median_translation_error_m"] is not None:
            line += (f", median error {s['median_translation_error_m']:.3f} m "
                     f"{s['median_rotation_error_deg']:.2f} deg")
        print(line + f", mean latency {s['latency_ms']['mean']:.0f} ms")
        print("recall (share of all queries within m/deg): "
              + ", ".join(f"{k} {100 * v:.1f}%" for k, v in s["recall"].items()))


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        run(args)
    except ClientError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    except OSError as e:  # e.g. a Point file that fails to read half-way
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
