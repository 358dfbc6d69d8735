"""`gmt bench`: every requested section of the figures, as one JSON-ready dict (schema: `gmt.bench`)."""

from __future__ import annotations

import os
import platform
import shutil
import tempfile
from pathlib import Path

from gmt.bench.alternatives import bench_alternatives
from gmt.bench.batching import bench_batching
from gmt.bench.cluster import bench_cluster, bench_scaleout
from gmt.bench.console import bench_console
from gmt.bench.device import bench_device
from gmt.bench.engine import bench_engine
from gmt.bench.failover import bench_failover
from gmt.bench.harness import SESSIONS, default_size_checkpoint
from gmt.bench.records import bench_records
from gmt.bench.serving import bench_serving
from gmt.bench.store import bench_store
from gmt.bench.store_ab import bench_store_ab
from gmt.bench.stream import bench_stream
from gmt.bench.training import bench_training


def machine() -> dict:
    """The machine the figures come from: CPU, cores, torch, platform, whether the native kernel builds."""
    import torch

    cpu = platform.processor()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    from gmt.model import native

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "platform": platform.platform(),
        "native_kernel": native.load() is not None,
    }


def _default(tmp: Path) -> Path:
    d = tmp / "bench-gmt"
    if not d.exists():
        default_size_checkpoint(d)
    return d


def run(
    checkpoint: Path | None,
    sections: tuple[str, ...],
    seconds: float,
    sessions: tuple[int, ...] = SESSIONS,
    baseline: str | None = None,
    device: str = "auto",
    replicas: tuple[int, ...] = (1, 2),
) -> dict:
    """Every requested section; a temporary default-size `window` checkpoint when none is given; `baseline`: the
    commit the batching, stream and store-ab sections compare with (None: each section's own); `device`: where
    the device section serves; `replicas`: the cluster section's deployments."""
    against = {"baseline": baseline} if baseline else {}
    result: dict = {"machine": machine()}
    tmp = Path(tempfile.mkdtemp(prefix="gmt-bench-"))
    try:
        if "engine" in sections:
            result["engine"] = bench_engine()
        if "serving" in sections:
            checkpoint = checkpoint or _default(tmp)
            if shutil.which("wrk") is None:
                result["serving"] = {"skipped": "wrk is not installed (apt-get install wrk)"}
            else:
                result["serving"] = bench_serving(checkpoint, sessions, seconds)
        if "store" in sections:
            if shutil.which("wrk") is None or shutil.which("redis-server") is None:
                result["store"] = {
                    "skipped": "wrk and redis-server are needed (apt-get install wrk redis-server)"
                }
            else:
                result["store"] = bench_store(checkpoint or _default(tmp), max(sessions), seconds)
        if "batching" in sections:
            if shutil.which("wrk") is None:
                result["batching"] = {"skipped": "wrk is not installed (apt-get install wrk)"}
            else:
                result["batching"] = bench_batching(
                    checkpoint or _default(tmp), max(sessions), seconds, **against
                )
        if "stream" in sections:
            result["stream"] = bench_stream(checkpoint or _default(tmp), max(sessions), seconds, **against)
        for section in ("store-ab", "store-ab-replicated"):
            if section not in sections:
                continue
            if shutil.which("wrk") is None or shutil.which("redis-server") is None:
                result[section] = {
                    "skipped": "wrk and redis-server are needed (apt-get install wrk redis-server)"
                }
            else:
                result[section] = bench_store_ab(
                    checkpoint or _default(tmp),
                    max(sessions),
                    seconds,
                    replicated=section.endswith("replicated"),
                    **against,
                )
        if "records" in sections:
            if shutil.which("wrk") is None or shutil.which("redis-server") is None:
                result["records"] = {
                    "skipped": "wrk and redis-server are needed (apt-get install wrk redis-server)"
                }
            else:
                result["records"] = bench_records(checkpoint or _default(tmp), 64, seconds)
        if "device" in sections:
            if shutil.which("wrk") is None:
                result["device"] = {"skipped": "wrk is not installed (apt-get install wrk)"}
            else:
                result["device"] = bench_device(checkpoint or _default(tmp), sessions, seconds, device)
        if "cluster" in sections:
            result["cluster"] = bench_scaleout(checkpoint or _default(tmp), max(sessions), seconds, replicas)
        if "soak" in sections:
            result["soak"] = bench_cluster(
                checkpoint or _default(tmp), max(sessions), 120.0 if seconds >= 8 else seconds
            )
        if "console" in sections:
            result["console"] = bench_console(checkpoint or _default(tmp), max(sessions), seconds)
        if "failover" in sections:
            result["failover"] = bench_failover(checkpoint or _default(tmp), max(sessions))
        if "training" in sections:
            result["training"] = bench_training()
        if "alternatives" in sections:
            result["alternatives"] = bench_alternatives(checkpoint or _default(tmp), sessions, seconds)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result
