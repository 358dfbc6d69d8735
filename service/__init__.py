"""The controllable-policy service: transport-agnostic core plus REST and gRPC adapters."""
