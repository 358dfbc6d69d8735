"""Goal-Masked Transformer: data, network, training, checkpoints, batched inference and evaluation."""
