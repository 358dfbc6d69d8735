"""Offline datasets as training reads them: Minari I/O, per-trajectory statistics and goal relabelling.

Generating data (behaviour agents, collection) is `gmt.datagen`'s job.
"""
