"""Offline datasets: behaviour agents, collection, Minari I/O, statistics and goal relabelling."""
