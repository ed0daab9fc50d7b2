"""gRPC stubs of proto/pntr/v1/localizer.proto, generated when the package is built (see setup.py).

`localizer_pb2` (messages, with a `.pyi`) and `localizer_pb2_grpc` (`LocalizerStub`) are written here
by `grpc_tools.protoc` during the build and shipped in the wheel; they are not kept in the repository.
"""
