"""Torch-free definitions shared by the client and the model side: segments and how they are measured, the
per-trajectory statistics, space descriptions, tables, environments made from a model's spec, and the plumbing of
the `gmt` command (which extras are installed, flags generated from dataclasses)."""
