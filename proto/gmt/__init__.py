"""gmt-service: Goal-Masked Transformers trained on offline trajectories and served as controllable policies.

One import package built from the repository's folders (pyproject.toml, `[tool.setuptools]`): `gmt.model`
(model/: network, training, evaluation, the engine), `gmt.service` (service/: the server and the `gmt` command),
`gmt.client` (clients/: the thin client) and `gmt.v1` (proto/gmt/v1: the generated gRPC stubs).
"""

__version__ = "0.1.0"
