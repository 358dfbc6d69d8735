"""The tables of docs/performance.md from a `gmt bench` result."""

from __future__ import annotations


def to_markdown(result: dict) -> str:
    """The tables of docs/performance.md from a `run` result."""
    lines = []
    m = result.get("machine", {})
    lines += [f"Machine: {m.get('cpu')}, {m.get('cores')} cores, torch {m.get('torch')}.", ""]
    if "engine" in result:
        lines += ["### Engine: ms per act step (one torch thread, window model 3 x 128, full history)", ""]
        paths = ("incremental", "incremental_torch", "recompute")
        if any(r["path"] == "incremental_bf16" for r in result["engine"]):
            paths = ("incremental", "incremental_bf16", "incremental_torch", "recompute")
        lines += ["| K | " + " | ".join(f"{p}, batch {b}" for b in (1, 64) for p in paths) + " |"]
        lines += ["|---|" + "---|" * (2 * len(paths))]
        rows = {(r["K"], r["path"], r["batch"]): r["ms_per_step"] for r in result["engine"]}
        for K in sorted({r["K"] for r in result["engine"]}):
            cells = [rows.get((K, p, b), float("nan")) for b in (1, 64) for p in paths]
            lines.append(f"| {K} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
        lines.append("")
    serving = result.get("serving", {})
    if "servers" in serving:
        lines += ["### Serving: acts/s (p50 / p99 ms) by concurrent sessions", ""]
        servers = serving["servers"]
        transports = ("rest", "rest_batch", "grpc_unary", "grpc_stream")
        counts = [r["sessions"] for r in next(iter(servers.values()))["rest"]]
        lines += ["| server | transport | " + " | ".join(f"{n} sessions" for n in counts) + " |"]
        lines += ["|---|---|" + "---|" * len(counts)]
        for kind, res in servers.items():
            for tr in transports:
                cells = [
                    f"{r['acts_per_s']:.0f} ({r['p50_ms']:.1f} / {r['p99_ms']:.1f})" for r in res.get(tr, [])
                ]
                lines.append(f"| {kind} | {tr} | " + " | ".join(cells) + " |")
        if "naive" in servers and "default" in servers:
            lines += ["", "Ratio default / naive, acts/s:", ""]
            lines += ["| transport | " + " | ".join(f"{n} sessions" for n in counts) + " |"]
            lines += ["|---|" + "---|" * len(counts)]
            for tr in transports:
                base = {r["sessions"]: r["acts_per_s"] for r in servers["naive"]["rest"]}
                cells = [
                    f"{r['acts_per_s'] / max(base.get(r['sessions'], 1), 1e-9):.1f}x"
                    for r in servers["default"][tr]
                ]
                lines.append(f"| {tr} vs naive rest | " + " | ".join(cells) + " |")
        if "memory" in serving:
            lines += [
                "",
                f"Memory per live session (RSS growth): {serving['memory']['rss_per_session_bytes']} bytes.",
            ]
        lines.append("")
    if "training" in result:
        t = result["training"]
        lines += [
            "### Training (default model, batch 64 x K 20, one thread)",
            "",
            f"{t['steps_per_s']} steps/s, {t['gflops_achieved']} GFLOP/s achieved in the matrix products; measured "
            f"GEMM rate {t['gemm_gflops']['fp32']} GFLOP/s fp32, {t['gemm_gflops']['bf16']} GFLOP/s bf16.",
            "",
        ]
    rec = result.get("records", {})
    if "stores" in rec:
        lines += [
            f"### Recording: REST acts/s (p50 / p99 ms) at {rec['sessions']} sessions, recorded and not, same server",
            "",
            "| store | not recorded | recorded | recorded / not |",
            "|---|---|---|---|",
        ]
        for store, res in rec["stores"].items():
            cells = [
                " / ".join(f"{r['acts_per_s']:.0f} ({r['p50_ms']:.1f} / {r['p99_ms']:.1f})" for r in res[k])
                for k in ("plain", "recorded")
            ]
            lines.append(f"| {store} | {cells[0]} | {cells[1]} | {res['recorded_vs_plain']} |")
        lines.append("")
    alt = result.get("alternatives", {})
    if alt:
        lines += ["### What a user would deploy instead", ""]
        ray = alt.get("ray_serve", {})
        if "skipped" in ray:
            lines += [f"Ray Serve: skipped ({ray['skipped']}).", ""]
        elif ray:
            lines += [
                "Ray Serve with `@serve.batch` (same checkpoint, REST one call per act, wrk): acts/s (p50 / p99 ms)",
                "",
            ]
            counts = [r["sessions"] for r in next(v for k, v in ray.items() if isinstance(v, list))]
            lines += ["| engine inside Ray Serve | " + " | ".join(f"{n} sessions" for n in counts) + " |"]
            lines += ["|---|" + "---|" * len(counts)]
            for path in ("recompute", "incremental"):
                cells = [
                    f"{r['acts_per_s']:.0f} ({r['p50_ms']:.1f} / {r['p99_ms']:.1f})"
                    for r in ray.get(path, [])
                ]
                lines.append(f"| {path} | " + " | ".join(cells) + " |")
            lines.append("")
        hf = alt.get("hf_decision_transformer", {})
        if "skipped" in hf:
            lines += [f"Hugging Face DecisionTransformerModel: skipped ({hf['skipped']}).", ""]
        elif hf:
            lines += [
                f"Hugging Face DecisionTransformerModel ({hf['config']}, {hf['params']} parameters): "
                f"{hf['steps_per_s']} training steps/s.",
                "",
            ]
    return "\n".join(lines)
