"""The server console's page (`GET /ui`): static files only (`static/`), served by the REST adapter.

The console is an adapter like REST and gRPC: its routes (`GET /sessions`, `GET /sessions/{id}/events` and the page)
are in `gmt.service.rest.console`; the feeds it shows are the service's own (`gmt.service.activity`: acts/s and last
latency per session; `gmt.service.events`: the per-session event feed).
"""
