"""`gmt cluster`: a deployment tool beside the service, not part of it. `supervisor` starts, stops and upgrades the
scale-out topology (Redis with Sentinel, `gmt serve` replicas, nginx) as local processes; it only runs `gmt serve`
and talks to the replicas over their public APIs, so nothing of `gmt.service` imports it."""
