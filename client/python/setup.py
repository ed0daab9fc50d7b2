"""Build steps of the pntr-client package that pyproject.toml cannot declare (metadata lives there).

- `build_py` generates the gRPC stubs from the localizer proto with `grpc_tools.protoc` (a build
  requirement) into `pntr_client/_proto/` of the build: `localizer_pb2.py`, `localizer_pb2.pyi` and
  `localizer_pb2_grpc.py`, so every wheel ships them and nothing is generated at run time. The proto
  is compiled as `pntr_client/_proto/localizer.proto`, so the generated modules import each other as
  `pntr_client._proto.*` and install no top-level `pntr` package. In an editable install
  (`pip install -e`) they are written into `src/pntr_client/_proto/` instead (git-ignored).
- `sdist` adds a copy of the proto to the archive (`proto/pntr/v1/localizer.proto` beside this file),
  so the archive builds on its own, away from the repository.
- Unless told otherwise (`--build-base`, `--egg-base`), builds and their egg-info go to a temporary
  folder removed at exit, not to `build/` and `src/` here: concurrent builds (parallel tests) cannot
  trip over each other, no stale module from an earlier build can end up in a wheel, and the source
  tree stays clean.

The proto is looked up first in the sdist's copy, then in the repository (`../../proto/`).
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py as _build_py
from setuptools.command.sdist import sdist as _sdist

HERE = Path(__file__).resolve().parent
PROTO_NAME = "pntr/v1/localizer.proto"
# The copy an sdist carries, then the repository's own.
PROTO_CANDIDATES = [HERE / "proto" / PROTO_NAME, HERE.parent.parent / "proto" / PROTO_NAME]
# Where the stubs go, relative to the build's (or the source's) package root.
STUB_PACKAGE = Path("pntr_client") / "_proto"
STUB_FILES = ["localizer_pb2.py", "localizer_pb2.pyi", "localizer_pb2_grpc.py"]


def find_proto() -> Path:
    """The localizer proto to compile (see PROTO_CANDIDATES); SystemExit naming both places if absent."""
    for p in PROTO_CANDIDATES:
        if p.is_file():
            return p
    raise SystemExit(
        "pntr-client: cannot find the localizer proto; looked for "
        + " and ".join(str(p) for p in PROTO_CANDIDATES)
        + " (build from the repository's client/python folder or from an sdist)"
    )


def generate_stubs(out_root: Path) -> list[Path]:
    """Compile the proto into `out_root / STUB_PACKAGE`; returns the files written."""
    from grpc_tools import protoc  # a build requirement (pyproject.toml)

    proto = find_proto()
    well_known = Path(protoc.__file__).parent / "_proto"  # google/protobuf/*.proto
    with tempfile.TemporaryDirectory(prefix="pntr-proto-") as tmp:
        # Compile a copy placed at the package path, so imports in the generated code are
        # `pntr_client._proto.localizer_pb2` rather than a top-level `pntr.v1`.
        staged = Path(tmp) / STUB_PACKAGE / "localizer.proto"
        staged.parent.mkdir(parents=True)
        shutil.copyfile(proto, staged)
        (out_root / STUB_PACKAGE).mkdir(parents=True, exist_ok=True)
        args = [
            "grpc_tools.protoc",
            f"-I{tmp}",
            f"-I{well_known}",
            f"--python_out={out_root}",
            f"--pyi_out={out_root}",
            f"--grpc_python_out={out_root}",
            (STUB_PACKAGE / "localizer.proto").as_posix(),
        ]
        rc = protoc.main(args)
    if rc != 0:
        raise SystemExit(f"pntr-client: grpc_tools.protoc failed on {proto} (exit {rc})")
    written = [out_root / STUB_PACKAGE / name for name in STUB_FILES]
    missing = [str(p) for p in written if not p.is_file()]
    if missing:
        raise SystemExit(f"pntr-client: grpc_tools.protoc did not write {', '.join(missing)}")
    return written


class build_py(_build_py):
    """The standard build_py, then the stubs generated into the build (or the source when editable)."""

    def run(self) -> None:
        super().run()
        root = HERE / "src" if getattr(self, "editable_mode", False) else Path(self.build_lib)
        for p in generate_stubs(root):
            self.announce(f"generated {p}", level=2)

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        outputs = list(super().get_outputs(include_bytecode))
        if not getattr(self, "editable_mode", False):
            outputs += [str(Path(self.build_lib) / STUB_PACKAGE / n) for n in STUB_FILES]
        return outputs


class sdist(_sdist):
    """The standard sdist, plus a copy of the proto so the archive builds without the repository."""

    def make_release_tree(self, base_dir: str, files: list[str]) -> None:
        super().make_release_tree(base_dir, files)
        dest = Path(base_dir) / "proto" / PROTO_NAME
        if not dest.exists():
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(find_proto(), dest)


def _temporary_build_base() -> str:
    path = tempfile.mkdtemp(prefix="pntr-client-build-")
    atexit.register(shutil.rmtree, path, True)
    return path


_SCRATCH = _temporary_build_base()
setup(
    cmdclass={"build_py": build_py, "sdist": sdist},
    options={"build": {"build_base": _SCRATCH}, "egg_info": {"egg_base": _SCRATCH}},
)
