"""`gmt.cluster.supervisor.free_port`: ports that another process can bind a moment later."""

import itertools
import socket

from gmt.cluster import supervisor as cluster


def test_ports_are_free_distinct_and_below_the_ephemeral_range():
    lo, _ = cluster._ephemeral_range()
    ports = [cluster.free_port() for _ in range(50)]
    assert len(set(ports)) == 50  # never the same port twice, though each is released at once
    if lo > 11_000:  # outgoing connections never take these as their local port
        assert all(10_000 <= p < lo for p in ports)
    for p in ports[:5]:
        with socket.socket() as s:
            s.bind(("127.0.0.1", p))  # nothing listens there


def test_a_taken_port_is_never_given(monkeypatch):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        draws = itertools.chain([busy, busy], itertools.count(20_000))  # the taken port, twice, then others

        class Draw:
            def randrange(self, a, b):
                return next(draws)

        monkeypatch.setattr(cluster.random, "SystemRandom", Draw)
        monkeypatch.setattr(cluster, "_ephemeral_range", lambda: (max(busy + 2, 20_001), 60999))
        assert cluster.free_port() != busy
