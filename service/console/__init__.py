"""The server console (`GET /ui`): per-session activity, the per-session event feed, the listing and the page.

- `activity`: acts/s and last latency of a session, kept in O(1) per act (stored with the session);
- `events`: the per-session event feed with bounded per-subscriber queues (`GET /sessions/{id}/events`);
- `routes`: `GET /sessions`, `GET /sessions/{id}/events` and the static page `GET /ui` (assets in `static/`).
"""
