"""gRPC stubs of proto/pntr/v1/localizer.proto, generated ahead of time and shipped in the package.

`localizer_pb2` (messages, with a `.pyi`) and `localizer_pb2_grpc` (`LocalizerStub`, `MapAdminStub`)
are written by `client/python/generate_proto.py` (grpc_tools.protoc) and committed; do not edit them.
After a change to the proto, run that script; `generate_proto.py --check` (run by
tests/python_client.rs) fails while they differ from the proto.
"""
