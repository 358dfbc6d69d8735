"""`GMT_NAIVE=1 gmt serve` is the exactness oracle of the default server; `gmt bench` measures what it says."""

import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_harness import RunningServer, ServeProcess, make_settings

from gmt.bench.cluster import bench_cluster
from gmt.bench.device import bench_device
from gmt.bench.engine import bench_engine
from gmt.bench.harness import cpp_toolchain_missing, rss_bytes
from gmt.bench.serving import bench_serving
from gmt.model.fixtures import tiny_checkpoint


@pytest.fixture(scope="module")
def window_ckpt(tmp_path_factory):
    d = tmp_path_factory.mktemp("window") / "tiny-window"
    tiny_checkpoint(d, name="tiny-window", attention="window", calibrated=True, context_length=4, n_layer=3)
    return d


def _episode(url: str, obs: np.ndarray) -> np.ndarray:
    with httpx.Client(base_url=url, timeout=30) as http:
        sid = http.post("/sessions", json={"goal": 0, "seed": 5}).json()["session_id"]
        out = []
        for t, o in enumerate(obs):
            if t == 20:
                assert (
                    http.put(f"/sessions/{sid}/goal", json={"goal": 2, "blend_steps": 5}).status_code == 200
                )
            r = http.post(f"/sessions/{sid}/act", json={"observation": o.tolist()})
            assert r.status_code == 200, r.text
            out.append(r.json()["action"])
    return np.asarray(out)


def test_naive_server_and_incremental_server_give_the_same_actions(window_ckpt):
    obs = np.random.default_rng(0).normal(size=(40, 17)).astype(np.float32)
    naive = ServeProcess("--checkpoints", str(window_ckpt), env={"GMT_NAIVE": "1"})
    try:
        info = naive.wait_serving()
        assert info["models"] == ["tiny-window"]
        loaded = next(r for r in naive.lines if r.get("msg") == "model loaded")
        assert loaded["engine"] == "recompute" and loaded["attention"] == "window"
        reference = _episode(naive.url, obs)
    finally:
        naive.kill()
    fast = RunningServer(make_settings(checkpoints=[window_ckpt])).start()
    try:
        assert fast.core.registry.get("tiny-window").engine.describe().path == "incremental"
        got = _episode(fast.url, obs)
    finally:
        fast.stop()
    np.testing.assert_allclose(got, reference, atol=1e-5, rtol=0)


def test_engine_section_times_both_paths_for_every_K_and_batch():
    from gmt.model import native

    rows = bench_engine(Ks=(4, 8), batches=(1, 3), steps=3)
    paths = ("incremental", "incremental_torch", "recompute")
    paths += ("incremental_bf16",) if native.has_bf16() else ()  # the bf16 products, where this CPU has them
    assert {(r["K"], r["path"], r["batch"]) for r in rows} == {
        (K, p, B) for K in (4, 8) for p in paths for B in (1, 3)
    }
    for r in rows:  # acts/s is the batch over the time of one step
        assert r["ms_per_step"] > 0 and r["acts_per_s"] == pytest.approx(
            r["batch"] / r["ms_per_step"] * 1000, rel=0.02
        )


def test_rss_bytes_sees_memory_being_touched():
    import os

    before = rss_bytes(os.getpid())
    block = np.ones(64 * 2**20, dtype=np.uint8)  # 64 MiB, every page written
    grown = rss_bytes(os.getpid()) - before
    assert before > 2**20 and 60 * 2**20 <= grown <= 80 * 2**20, (before, grown)
    del block


@pytest.mark.skipif(shutil.which("wrk") is None, reason="wrk is not installed (apt-get install wrk)")
def test_device_section_times_both_engines_and_alternates_two_live_servers(window_ckpt):
    """On a machine without a GPU the device is the CPU's torch step: the same code as on `cuda`."""
    res = bench_device(window_ckpt, sessions=(1, 3), seconds=1.0, device="cpu", rounds=2, steps=3)
    assert res["device"] == "cpu" and res["device_name"] == "cpu"
    assert {(r["path"], r["batch"]) for r in res["engine"]} == {
        (p, b) for p in ("default", "device") for b in (1, 3)
    }
    assert {r["kernel"] for r in res["engine"] if r["path"] == "device"} == {"torch"}
    for r in res["engine"]:
        assert r["acts_per_s"] == pytest.approx(r["batch"] / r["ms_per_step"] * 1000, rel=0.02)
    for server in ("cpu", "device"):
        for load in ("rest_batch", "rest"):
            rows = res["served"][server][load]
            assert [r["sessions"] for r in rows] == [1, 3]
            for r in rows:  # two rounds each, over which acts/s is the mean
                acts = [x["acts_per_s"] for x in r["rounds"]]
                assert r["errors"] == 0 and len(acts) == 2 and min(acts) > 0, r
                assert r["acts_per_s"] == pytest.approx(sum(acts) / 2, abs=0.1)
    for load in ("rest_batch", "rest"):
        cpu, dev = res["served"]["cpu"][load][1], res["served"]["device"][load][1]
        assert res["device_vs_cpu"][load]["3"] == round(dev["acts_per_s"] / cpu["acts_per_s"], 3)


@pytest.mark.skipif(shutil.which("wrk") is None, reason="wrk is not installed (apt-get install wrk)")
def test_serving_section_drives_every_transport_without_errors(window_ckpt):
    res = bench_serving(window_ckpt, sessions=(1, 3), seconds=1.0, servers=("default",))
    points = res["servers"]["default"]
    assert set(points) == {"rest", "rest_batch", "grpc_unary", "grpc_stream"}
    for transport, rows in points.items():
        assert [r["sessions"] for r in rows] == [1, 3], transport
        for r in rows:
            assert r["errors"] == 0 and r["acts_per_s"] > 0 and 0 < r["p50_ms"] <= r["p99_ms"], (transport, r)
    # The server's own growth per session (a tiny model: well under a MiB), not its whole RSS (hundreds of MiB).
    assert abs(res["memory"]["rss_per_session_bytes"]) < 2**20, res["memory"]


@pytest.mark.skipif(
    shutil.which("wrk") is None or shutil.which("redis-server") is None,
    reason="needs wrk and redis-server (apt-get install wrk redis-server)",
)
def test_records_section_measures_recorded_and_plain_sessions_of_one_server(window_ckpt):
    from gmt.bench.records import bench_records
    from gmt.bench.report import to_markdown

    res = bench_records(window_ckpt, sessions=3, seconds=1.0, rounds=1)
    for store in ("memory", "redis"):
        r = res["stores"][store]
        for row in r["plain"] + r["recorded"]:
            assert row["errors"] == 0 and row["sessions"] == 3 and row["acts_per_s"] > 0, (store, row)
        # Every act of the recorded set was kept (the first, setup act too), and each session's file written.
        assert r["recorded_steps"] >= r["recorded"][0]["acts_per_s"] * 0.5 and r["files_written"] == 3, r
        assert r["recorded_vs_plain"] == round(r["acts_per_s"]["recorded"] / r["acts_per_s"]["plain"], 3)
    assert "### Recording: REST acts/s" in to_markdown({"records": res})


@pytest.mark.skipif(
    any(
        shutil.which(p) is None and not Path("/usr/sbin", p).exists()
        for p in ("wrk", "nginx", "redis-server")
    ),
    reason="needs wrk, nginx and redis-server (apt-get install wrk nginx redis-server)",
)
def test_cluster_section_loads_two_replicas_through_nginx_without_errors(window_ckpt):
    res = bench_cluster(window_ckpt, sessions=4, seconds=1.0)
    for wave in (res["load"], res["second_wave"]):
        assert wave["errors"] == 0 and wave["acts_per_s"] > 0, wave
    assert set(res["rss_bytes"]["live"]) == {"gmt-1", "gmt-2"}
    for when, per_replica in res[
        "rss_bytes"
    ].items():  # each is a live serving process (torch alone is ~100 MiB)
        assert all(rss > 50 * 2**20 for rss in per_replica.values()), (when, per_replica)
    total = {when: sum(d.values()) for when, d in res["rss_bytes"].items()}
    assert res["rss_per_live_session_bytes"] == (total["live"] - total["started"]) // 4
    assert res["rss_growth_second_wave_bytes"] == total["second_wave"] - total["live"]


@pytest.mark.skipif(
    shutil.which("wrk") is None or shutil.which("redis-server") is None,
    reason="needs wrk and redis-server (apt-get install wrk redis-server)",
)
def test_store_section_alternates_rounds_over_three_live_servers(window_ckpt):
    from gmt.bench.store import bench_store

    res = bench_store(window_ckpt, sessions=3, seconds=2.0, rounds=2)
    for store in ("memory", "redis", "redis_unix", "replicated"):
        for load in ("rest_1_session", "rest", "rest_batch"):
            row = res["stores"][store][load]
            assert len(row["rounds"]) == 2 and row["errors"] == 0 and row["acts_per_s"] > 0, (
                store,
                load,
                row,
            )
            assert row["acts_per_s"] == round(sum(r["acts_per_s"] for r in row["rounds"]) / 2, 1)
        assert res["stores"][store]["rest_1_session"]["sessions"] == 1
        assert res["stores"][store]["rest"]["sessions"] == 3
    m, r = res["stores"]["memory"], res["stores"]["redis"]
    assert res["redis_vs_memory"]["rest"] == round(r["rest"]["acts_per_s"] / m["rest"]["acts_per_s"], 3)
    assert len(res["redis_vs_memory"]["p50_1_session_added_ms_rounds"]) == 2


def test_batching_section_serves_two_commits_and_measures_idle_neighbours(window_ckpt):
    from gmt.bench.batching import bench_batching

    res = bench_batching(window_ckpt, sessions=3, seconds=2.0, rounds=1, baseline="HEAD", current="HEAD")
    for server in ("current", "baseline"):
        for load in ("alone", "idle_neighbours", "rest", "rest_batch"):
            row = res["servers"][server][load]
            assert row["errors"] == 0 and row["acts_per_s"] > 0 and len(row["rounds"]) == 1, (
                server,
                load,
                row,
            )
        assert res["servers"][server]["idle_neighbours"]["sessions"] == 1
        assert res["servers"][server]["rest"]["sessions"] == 3
    v = res["servers"]
    assert res["vs_baseline"]["rest"] == round(
        v["current"]["rest"]["acts_per_s"] / v["baseline"]["rest"]["acts_per_s"], 3
    )


def test_stream_section_loads_control_and_act_batch_on_two_commits(window_ckpt):
    from gmt.bench.stream import bench_stream

    res = bench_stream(window_ckpt, sessions=3, seconds=2.0, rounds=1, baseline="HEAD", current="HEAD")
    for server in ("current", "baseline"):
        control, batch, every = (res["servers"][server][k] for k in ("control", "act_batch", "control_all"))
        assert control["sessions"] == 1 and batch["sessions"] == 3 and every["sessions"] == 3
        for row in (control, batch, every):
            assert row["errors"] == 0 and row["acts_per_s"] > 0 and len(row["rounds"]) == 1, (server, row)
    v = res["servers"]
    assert res["vs_baseline"]["control_p50"] == round(
        v["current"]["control"]["p50_ms"] / v["baseline"]["control"]["p50_ms"], 3
    )
    # The robot loop from the C++ client too, wherever it can be built (CI installs gRPC's C++ toolchain).
    assert ("control_cpp" in v["current"]) == (not cpp_toolchain_missing())
    if "control_cpp" in v["current"]:
        for server in ("current", "baseline"):
            row = v[server]["control_cpp"]
            assert row["errors"] == 0 and row["acts_per_s"] > 0 and 0 < row["p50_ms"] <= row["p99_ms"], row


def test_grpc_client_counts_act_batch_items_that_failed(window_ckpt):
    """ActBatch acts/s counts answered items only: an unknown session's item is an error, not an act."""
    from gmt.bench.harness import grpc_client, open_sessions, start_server

    proc, info = start_server(window_ckpt, naive=False)
    try:
        sids = open_sessions(f"http://127.0.0.1:{info['rest_port']}", info["models"][0], 2)
        res = grpc_client(f"127.0.0.1:{info['grpc_port']}", [*sids, "no-such-session"], 1.0, "batch")
    finally:
        proc.terminate()
        proc.wait(30)
    assert res["sessions"] == 3 and res["errors"] > 0 and res["acts_per_s"] > 0


def test_store_ab_section_runs_four_servers_and_takes_each_rounds_ratio(window_ckpt):
    from gmt.bench.store_ab import bench_store_ab

    res = bench_store_ab(window_ckpt, sessions=3, seconds=2.0, rounds=2, baseline="HEAD", current="HEAD")
    assert set(res["servers"]) == {"current-memory", "current-redis", "baseline-memory", "baseline-redis"}
    for name, loads in res["servers"].items():
        for load in ("rest", "rest_batch"):
            row = loads[load]
            assert len(row["rounds"]) == 2 and row["errors"] == 0 and row["acts_per_s"] > 0, (name, load, row)
    for load in ("rest", "rest_batch"):
        for c in ("current", "baseline"):
            mem, red = res["servers"][f"{c}-memory"][load], res["servers"][f"{c}-redis"][load]
            want = [
                round(b["acts_per_s"] / a["acts_per_s"], 3)
                for a, b in zip(mem["rounds"], red["rounds"], strict=True)
            ]
            assert res["ratios"][load][c]["rounds"] == want
        d = res["difference"][load]
        cur, base = res["ratios"][load]["current"]["mean"], res["ratios"][load]["baseline"]["mean"]
        assert d["current_minus_baseline"] == round(cur - base, 3) and d["standard_error"] >= 0
