"""Build steps of the pntr-client package that pyproject.toml cannot declare (metadata lives there).

The gRPC stubs (`src/pntr_client/_proto/localizer_pb2.py`, `.pyi`, `localizer_pb2_grpc.py`) are
generated from proto/pntr/v1/localizer.proto ahead of time by `generate_proto.py` and committed, so
building and installing need nothing beyond setuptools, and installing only the runtime dependencies.

- `build_py` refuses to build a package without those stubs, naming the command that makes them.
- Unless told otherwise (`--build-base`, `--egg-base`), builds and their egg-info go to a temporary
  folder removed at exit, not to `build/` and `src/` here: concurrent builds (parallel tests) cannot
  trip over each other, no stale module from an earlier build can end up in a wheel, and the source
  tree stays clean.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py as _build_py

HERE = Path(__file__).resolve().parent
STUBS = HERE / "src" / "pntr_client" / "_proto"
STUB_FILES = ["localizer_pb2.py", "localizer_pb2.pyi", "localizer_pb2_grpc.py"]


class build_py(_build_py):
    """The standard build_py, after checking that the committed stubs are present."""

    def run(self) -> None:
        missing = [name for name in STUB_FILES if not (STUBS / name).is_file()]
        if missing:
            raise SystemExit(
                f"pntr-client: {', '.join(missing)} missing from {STUBS}: generate them with "
                "`python client/python/generate_proto.py` (needs grpcio-tools; see that script)"
            )
        super().run()


def _temporary_build_base() -> str:
    path = tempfile.mkdtemp(prefix="pntr-client-build-")
    atexit.register(shutil.rmtree, path, True)
    return path


_SCRATCH = _temporary_build_base()
setup(
    cmdclass={"build_py": build_py},
    options={"build": {"build_base": _SCRATCH}, "egg_info": {"egg_base": _SCRATCH}},
)
