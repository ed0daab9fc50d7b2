"""`pntr-client` (also `python -m pntr_client`): localize HPointLoc query frames against a running
pntr-server and report each pose's error against the file's ground truth, then a summary.

Usage:
  pntr-client --addr HOST:PORT --dataset DIR --scene NAME [--point N] [--queries K]
              [--token T | --token-file F] [--tls-ca PEM] [--json]

Exit status: 0 when every query was answered (LOCALIZED or NOT_LOCALIZED), 1 when the server could
not be reached or answered an RPC with an error, 2 for bad arguments or unreadable input files.
Errors are one `error: ...` line on stderr. Reading the dataset needs h5py (`pntr-client[hpointloc]`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from pntr_client.client import Client
from pntr_client.errors import PntrError
from pntr_client.hpointloc import DATASET_DIR, DatasetError, point_files, read_point, require_h5py

# (metres, degrees) thresholds of the evaluation protocol (same as `pntr eval`).
THRESHOLDS: list[tuple[float, float]] = [(5.0, 20.0), (1.0, 10.0), (0.5, 5.0), (0.25, 2.0)]


class CliError(Exception):
    """An error to report in one line, with the exit status to end with."""

    def __init__(self, message: str, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code


# --- errors of a pose ----------------------------------------------------------------------------


def _quat_mul(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float, float]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _normalised(q: Sequence[float]) -> tuple[float, ...]:
    n = math.sqrt(sum(c * c for c in q))
    return tuple(c / n for c in q)


def rotation_error_deg(q_a: Iterable[float], q_b: Iterable[float]) -> float:
    """Geodesic angle between two rotations given as (w, x, y, z) quaternions, degrees in 0..180."""
    a, b = _normalised([float(c) for c in q_a]), _normalised([float(c) for c in q_b])
    d = _quat_mul((a[0], -a[1], -a[2], -a[3]), b)
    return math.degrees(2.0 * math.atan2(math.sqrt(d[1] ** 2 + d[2] ** 2 + d[3] ** 2), abs(d[0])))


def translation_error_m(t_a: Iterable[float], t_b: Iterable[float]) -> float:
    """Euclidean distance between two positions, metres."""
    return math.sqrt(sum((float(x) - float(y)) ** 2 for x, y in zip(t_a, t_b, strict=True)))


def _median(xs: list[float]) -> float | None:
    xs = sorted(xs)
    if not xs:
        return None
    m = len(xs) // 2
    return xs[m] if len(xs) % 2 else 0.5 * (xs[m - 1] + xs[m])


def summarise(results: list[dict[str, Any]]) -> dict[str, Any]:
    """The summary of per-query results: counts, median errors, recall at THRESHOLDS, latency (ms)."""
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
        "latency_ms": {
            "mean": sum(lat) / n if n else None,
            "median": _median(lat),
            "max": max(lat) if lat else None,
        },
    }


# --- command line --------------------------------------------------------------------------------


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    """The parsed arguments (argparse exits with status 2 on a mistake)."""
    p = argparse.ArgumentParser(
        prog="pntr-client",
        description="Localize HPointLoc query frames with a running pntr-server; print pose and error.",
    )
    p.add_argument("--addr", default="127.0.0.1:50051", help="server address HOST:PORT [%(default)s]")
    p.add_argument(
        "--dataset", required=True, help=f"dataset folder (the one holding {DATASET_DIR}/, or that folder itself)"
    )
    p.add_argument("--scene", required=True, help="scene name (folder under HPointLoc_dataset)")
    p.add_argument("--point", type=int, help="only this Point index [all Points of the scene]")
    p.add_argument("--queries", type=int, metavar="K", help="at most the first K queries of each Point [all]")
    p.add_argument("--map-id", default="", help="map to localize in [the server's only map]")
    p.add_argument(
        "--intrinsics",
        metavar="FX,FY,CX,CY",
        help="camera intrinsics in pixels [omitted: the server's HPointLoc camera]",
    )
    p.add_argument(
        "--token",
        default=os.environ.get("PNTR_TOKEN"),
        help="bearer token (sent as `authorization: Bearer <T>`) [$PNTR_TOKEN]",
    )
    p.add_argument("--token-file", help="read the bearer token from this file")
    p.add_argument("--tls-ca", metavar="PEM", help="use TLS, trusting the CA certificate(s) in this file")
    p.add_argument("--tls-server-name", help="expect this name in the server certificate [host of --addr]")
    p.add_argument("--timeout", type=float, default=60.0, help="deadline of each Localize call, s [%(default)s]")
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=10.0,
        help="how long to wait for the server to answer at all, s [%(default)s]",
    )
    # Kept so older command lines still work: the stubs are now built into the package.
    p.add_argument("--proto", help="ignored (the gRPC stubs are built into the package)")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of lines")
    args = p.parse_args(argv)
    if args.queries is not None and args.queries < 1:
        p.error("--queries must be at least 1")
    if not args.timeout > 0:
        p.error("--timeout must be positive")
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


def _rpc_error(e: PntrError, addr: str, what: str) -> CliError:
    """A one-line CliError for a failed call, with a hint for the common cases."""
    if e.code == "UNAVAILABLE":
        return CliError(f"cannot reach pntr-server at {addr} ({what}): UNAVAILABLE: {e.details}")
    if e.code == "UNAUTHENTICATED":
        return CliError(
            f"{what}: UNAUTHENTICATED: {e.details} (pass the server's token with --token, --token-file or PNTR_TOKEN)"
        )
    return CliError(f"{what}: {e.code}: {e.details}")


def _fmt(r: dict[str, Any]) -> str:
    if r["status"] != "LOCALIZED":
        cause = f"{r['cause']}: " if r.get("cause") else ""
        return f"{r['status']}  ({cause}{r['reason']})"
    t, q = r["translation"], r["rotation_wxyz"]
    return (
        f"LOCALIZED  t=({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) "
        f"q=({q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}, {q[3]:.4f})  "
        f"err {r['translation_error_m']:.3f} m {r['rotation_error_deg']:.2f} deg  "
        f"conf {r['confidence']:.2f}  inliers {r['inliers']}  match {r['matched_image_id']}"
    )


def run(args: argparse.Namespace) -> None:
    """Localize the selected queries and print the results; raises CliError / DatasetError."""
    files = point_files(args.dataset, args.scene, args.point)
    require_h5py()  # before connecting: without it no query can be read
    if args.proto:
        print("note: --proto is ignored: the gRPC stubs are built into the pntr-client package", file=sys.stderr)
    ca: bytes | None = None
    if args.tls_ca is not None:
        try:
            ca = Path(args.tls_ca).read_bytes()
        except OSError as e:
            raise CliError(f"cannot read --tls-ca {args.tls_ca}: {e.strerror}", 2) from e
    with Client(args.addr, args.token, ca, tls_server_name=args.tls_server_name, timeout_s=args.timeout) as client:
        try:
            info = client.map_info(args.map_id, wait_s=args.connect_timeout)
        except PntrError as e:
            if e.code == "DEADLINE_EXCEEDED":
                raise CliError(
                    f"cannot reach pntr-server at {args.addr}: no answer within {args.connect_timeout:g} s"
                ) from e
            raise _rpc_error(e, args.addr, "GetMapInfo") from e
        if not args.json:
            print(
                f"server {args.addr}: map {info.map_id} ({info.images} images, {info.points} Points, "
                f"preset {info.preset}, axes {info.camera_axes})"
            )
        results = []
        for point, path in files:
            for i, rgb, depth, gps, quat in read_point(path, args.queries):
                qid = f"{args.scene}/point{point}/q{i}"
                t0 = time.perf_counter()
                try:
                    a = client.localize(rgb, depth, args.intrinsics, args.map_id, request_id=qid)
                except PntrError as e:
                    raise _rpc_error(e, args.addr, f"Localize {qid}") from e
                except ValueError as e:
                    raise CliError(f"{qid}: {e}", 2) from e
                ms = (time.perf_counter() - t0) * 1e3
                r: dict[str, Any] = {
                    "query": qid,
                    "status": a.status,
                    "reason": a.reason,
                    "cause": a.cause,
                    "confidence": a.confidence,
                    "inliers": a.inliers,
                    "matched_image_id": a.matched_image_id,
                    "mode": a.mode,
                    "latency_ms": ms,
                    "server_ms": dict(a.stage_ms),
                    "gt_translation": [float(v) for v in gps],
                    "gt_rotation_wxyz": [float(v) for v in quat],
                }
                if a.translation is not None and a.rotation_wxyz is not None:
                    r["translation"] = [float(v) for v in a.translation]
                    r["rotation_wxyz"] = list(a.rotation_wxyz)
                    r["translation_error_m"] = translation_error_m(r["translation"], gps)
                    r["rotation_error_deg"] = rotation_error_deg(r["rotation_wxyz"], quat)
                results.append(r)
                if not args.json:
                    print(f"{qid}  {_fmt(r)}  {ms:.0f} ms", flush=True)
    summary = summarise(results)
    if args.json:
        server = {
            "addr": args.addr,
            "map_id": info.map_id,
            "images": info.images,
            "points": info.points,
            "preset": info.preset,
            "camera_axes": info.camera_axes,
        }
        print(json.dumps({"server": server, "queries": results, "summary": summary}, indent=1))
        return
    s = summary
    if not s["queries"]:
        print("summary: no queries")
        return
    line = f"summary: {s['localized']}/{s['queries']} LOCALIZED ({100 * s['localized_share']:.1f}%)"
    if s["median_translation_error_m"] is not None:
        line += f", median error {s['median_translation_error_m']:.3f} m {s['median_rotation_error_deg']:.2f} deg"
    print(line + f", mean latency {s['latency_ms']['mean']:.0f} ms")
    print(
        "recall (share of all queries within m/deg): "
        + ", ".join(f"{k} {100 * v:.1f}%" for k, v in s["recall"].items())
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 answered, 1 RPC failure, 2 bad input)."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        run(args)
    except CliError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    except DatasetError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # e.g. a Point file that fails to read half-way
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
