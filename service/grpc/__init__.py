"""gRPC adapter (grpc.aio)."""
