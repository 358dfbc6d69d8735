"""gmt-service: Goal-Masked Transformers trained on offline trajectories and served as controllable policies.

One import package built from the repository's folders (pyproject.toml, `[tool.setuptools]`):

- `gmt.model` (model/): network, training, evaluation, checkpoints and the batched inference engine; its `data`
  reads the offline datasets and relabels their goals;
- `gmt.datagen` (datagen/): the data lab that generates those datasets (behaviour agents, collection);
- `gmt.service` (service/): the server (REST, gRPC, sessions) and the `gmt` command;
- `gmt.client` (clients/): the thin client;
- `gmt.common` (common/): torch-free definitions the client and the model side share;
- `gmt.bench` (benchmarks/): `gmt bench`;
- `gmt.v1` (proto/gmt/v1): the generated gRPC stubs (this folder is `gmt` so that their own
  `from gmt.v1 import ...` resolves here).
"""

__version__ = "0.1.0"
