#!/usr/bin/env python3
"""Regenerate, or check, the gRPC stubs the pntr-client package ships in `src/pntr_client/_proto/`.

    python client/python/generate_proto.py           # rewrite the stubs from proto/pntr/v1/localizer.proto
    python client/python/generate_proto.py --check   # regenerate into a temporary folder and compare

The stubs (`localizer_pb2.py`, `localizer_pb2.pyi`, `localizer_pb2_grpc.py`) are committed, so
installing the package needs only its runtime dependencies. Run this after every change to the
proto and commit the result; `tests/python_client.rs` runs `--check` and fails when they drift.

Needs grpcio-tools at GRPCIO_TOOLS_VERSION (scripts/setup.sh installs it into .deps/venv):
`.deps/venv/bin/python client/python/generate_proto.py`. The generated code names the lowest
grpcio and protobuf it runs with (pyproject.toml's dependency ranges follow them), so writing the
stubs with another version is refused. `--check` with another version compares only what the stubs
describe (the proto's serialized file descriptor embedded in `localizer_pb2.py`) and says so.

The proto is compiled as `pntr_client/_proto/localizer.proto` (a copy placed there in a temporary
folder), so the generated modules import each other as `pntr_client._proto.*` and nothing needs a
top-level `pntr` package. Exit status: 0 done / identical, 1 the stubs differ from the proto (--check),
2 a tool or file is missing.
"""

from __future__ import annotations

import argparse
import ast
import shutil
import sys
import tempfile
from importlib import metadata
from pathlib import Path
from typing import NoReturn

HERE = Path(__file__).resolve().parent
PROTO = HERE.parent.parent / "proto" / "pntr" / "v1" / "localizer.proto"
SRC = HERE / "src"
# The package path the proto is compiled under, relative to the source root (src/).
STUB_PACKAGE = Path("pntr_client") / "_proto"
STUB_FILES = ("localizer_pb2.py", "localizer_pb2.pyi", "localizer_pb2_grpc.py")
# The version the committed stubs are written with (scripts/setup.sh's GRPC_VERSION).
GRPCIO_TOOLS_VERSION = "1.85.1"


def fail(message: str) -> NoReturn:
    """End with exit status 2 (a tool or file is missing, protoc failed), `message` on stderr."""
    print(f"generate_proto: {message}", file=sys.stderr)
    sys.exit(2)


def installed_tools_version() -> str:
    """The installed grpcio-tools version; exit status 2 saying how to get it when it is missing."""
    try:
        import grpc_tools  # noqa: F401
    except ImportError:
        fail(
            f"grpcio-tools is not installed in {sys.executable}: use .deps/venv/bin/python "
            f"(scripts/setup.sh), or pip install grpcio-tools=={GRPCIO_TOOLS_VERSION}"
        )
    return metadata.version("grpcio-tools")


def generate(proto: Path, out_root: Path) -> list[Path]:
    """Compile `proto` into `out_root / STUB_PACKAGE`; returns the files written."""
    from grpc_tools import protoc

    well_known = Path(protoc.__file__).parent / "_proto"  # google/protobuf/*.proto
    with tempfile.TemporaryDirectory(prefix="pntr-proto-") as tmp:
        staged = Path(tmp) / STUB_PACKAGE / "localizer.proto"
        staged.parent.mkdir(parents=True)
        shutil.copyfile(proto, staged)
        (out_root / STUB_PACKAGE).mkdir(parents=True, exist_ok=True)
        rc = protoc.main(
            [
                "grpc_tools.protoc",
                f"-I{tmp}",
                f"-I{well_known}",
                f"--python_out={out_root}",
                f"--pyi_out={out_root}",
                f"--grpc_python_out={out_root}",
                (STUB_PACKAGE / "localizer.proto").as_posix(),
            ]
        )
    if rc != 0:
        fail(f"grpc_tools.protoc failed on {proto} (exit {rc})")
    written = [out_root / STUB_PACKAGE / name for name in STUB_FILES]
    missing = [str(p) for p in written if not p.is_file()]
    if missing:
        fail(f"grpc_tools.protoc did not write {', '.join(missing)}")
    return written


def serialized_descriptor(pb2_file: Path) -> bytes | None:
    """The serialized FileDescriptorProto a generated `*_pb2.py` embeds (its AddSerializedFile
    argument), or None when the file holds none."""
    tree = ast.parse(pb2_file.read_text(encoding="utf-8"), str(pb2_file))
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "AddSerializedFile"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, bytes)
        ):
            return node.args[0].value
    return None


def check(proto: Path, tools_version: str) -> int:
    """Compare the committed stubs with ones generated now from `proto`; the exit status."""
    shipped = SRC / STUB_PACKAGE
    rerun = f"run `python {Path(__file__).resolve().relative_to(HERE.parent.parent)}` and commit the result"
    missing = [n for n in STUB_FILES if not (shipped / n).is_file()]
    if missing:
        print(f"generate_proto: {', '.join(missing)} missing from {shipped}: {rerun}")
        return 1
    with tempfile.TemporaryDirectory(prefix="pntr-stubs-") as tmp:
        fresh = Path(tmp) / STUB_PACKAGE
        generate(proto, Path(tmp))
        if tools_version == GRPCIO_TOOLS_VERSION:
            differ = [n for n in STUB_FILES if (shipped / n).read_bytes() != (fresh / n).read_bytes()]
            if differ:
                print(
                    f"generate_proto: {', '.join(differ)} in {shipped} differ from what {proto} generates "
                    f"(grpcio-tools {tools_version}): {rerun}"
                )
                return 1
            print(f"generate_proto: the stubs in {shipped} match {proto} (grpcio-tools {tools_version}, byte for byte)")
            return 0
        want = serialized_descriptor(fresh / "localizer_pb2.py")
        have = serialized_descriptor(shipped / "localizer_pb2.py")
    if want is None or have is None or want != have:
        print(
            f"generate_proto: {shipped / 'localizer_pb2.py'} does not describe {proto}: its serialized file "
            f"descriptor differs; {rerun} (with grpcio-tools {GRPCIO_TOOLS_VERSION})"
        )
        return 1
    print(
        f"generate_proto: the stubs in {shipped} describe {proto} (file descriptors equal); compared with "
        f"grpcio-tools {tools_version}, not {GRPCIO_TOOLS_VERSION}, so the generated text itself was not compared"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true", help="compare the committed stubs with the proto; change nothing")
    p.add_argument("--proto", type=Path, default=PROTO, help="the proto to compile [%(default)s]")
    args = p.parse_args(argv)
    if not args.proto.is_file():
        fail(f"{args.proto} not found")
    version = installed_tools_version()
    if args.check:
        return check(args.proto, version)
    if version != GRPCIO_TOOLS_VERSION:
        print(
            f"generate_proto: grpcio-tools {version} is installed; the stubs are written with "
            f"{GRPCIO_TOOLS_VERSION} (pyproject.toml's grpcio / protobuf ranges follow it): install that "
            f"version, or change GRPCIO_TOOLS_VERSION here, scripts/setup.sh's GRPC_VERSION and those "
            f"ranges together",
            file=sys.stderr,
        )
        return 2
    for path in generate(args.proto, SRC):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
