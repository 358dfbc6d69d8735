"""`gmt bench`: engine, serving and training figures as JSON, each beside the naive baseline of the same run.

Schema (top level): `machine` {cpu, cores, torch, platform, native_kernel}, `engine`, `serving`, `store`,
`batching`, `stream`, `cluster`, `soak`, `console`, `failover`, `training`, `alternatives`.

- `engine`: [{K, path ("incremental" | "incremental_bf16" | "incremental_torch" | "recompute"), batch,
  ms_per_step, acts_per_s}] for a random-weight `window` model of the default size (3 layers, 128 wide,
  HalfCheetah shapes), one torch thread; `incremental` is the served path (the native kernel when it builds here),
  `incremental_bf16` the native step with bf16 products (`--precision bf16`; only where the CPU has AVX-512 BF16),
  `incremental_torch` the same step in torch operations.
- `serving`: {model, servers: {naive | default: {rest | rest_batch | grpc_unary | grpc_stream: [{sessions,
  acts_per_s, p50_ms, p99_ms, errors}]}}, memory: {rss_per_session_bytes}}. REST load comes
  from wrk (one thread, one connection per session; `rest_batch` is one connection posting every session's
  observation to `POST /act`, p50/p99 per call); gRPC load from a separate client process.
- `cluster`: {sessions, cores, points: [{deployment, rest, rest_batch}]}: one in-memory `gmt serve`, then
  `gmt cluster` with each of `--replicas` (default 1 and 2) replicas behind nginx (Redis with Sentinel), same load,
  same run.
- `device`: {model, device, device_name, sessions, engine: [{path (default | device), device, kernel, batch,
  ms_per_step, acts_per_s}], served: {cpu | device: {rest_batch | rest: [{sessions, acts_per_s, p50_ms, p99_ms,
  errors, rounds}]}}, device_vs_cpu}: the checkpoint's engine and `gmt serve --device` (`--device`, default auto)
  against the default CPU path, both servers up at once, rounds alternated.
- `soak`: wrk's REST load through `gmt cluster` (nginx, two replicas) for 120 s: errors, latency, each
  replica's memory through two waves of sessions.
- `console`: {rounds: [{without_console, with_console, console_events, console_listings}], median_acts_per_s,
  with_vs_without}: REST acts/s with and without an open server console (`/ui`), same server, rounds alternated.
- `failover`: the Redis primary of `gmt cluster` killed under load (`gmt.bench.failover`): {sessions, killed,
  promoted, resume_s, retried_answers (by kind), lost_sessions, sessions_unlike_twin, ...}.
- `training`: {steps_per_s, gflops_achieved, gemm_gflops: {fp32, bf16}} for the default model and batch.
- `store`: {stores: {memory | redis | redis_unix | replicated: {rest, rest_batch, rest_1_session: {..., rounds}}},
  redis_vs_memory, redis_unix_vs_memory and replicated_vs_memory: {rest, rest_batch,
  p50_1_session_added_ms(_rounds)}}: the same server with sessions in memory, in a local redis-server reached over
  loopback TCP and over its Unix socket, and in a Redis primary with AOF (`everysec`) and one replica with
  `--store-min-replicas 1` (as `make cluster` deploys it), all four up at once, rounds alternated.
- `batching`: {sessions, baseline, servers: {current | baseline: {alone | idle_neighbours | rest | rest_batch:
  {..., rounds}}}, idle_vs_alone: {current, baseline}, vs_baseline: {rest, rest_batch}}: one session's REST p50
  alone and beside `sessions - 1` idle sessions of its model, then `sessions` acting, for this checkout's server
  and a baseline commit's (`git archive`, run from this environment), both up at once, rounds alternated.
- `stream`: {sessions, baseline, servers: {current | baseline: {control | control_cpp | act_batch | control_all:
  {..., rounds}}}, vs_baseline: {control_acts_per_s, control_cpp_acts_per_s, act_batch_acts_per_s,
  control_all_acts_per_s, control_p50, control_p99, control_cpp_p50}}: one session's Control stream (one act at a
  time; `control_cpp` the same from the C++ client, `clients/cpp`, present only where it can be built), `sessions`
  sessions per `ActBatch` call and `sessions` Control streams at once, from a fresh client process per round, for
  the same two servers as `batching`, both up at once, rounds alternated.
- `alternatives`: Ray Serve / Hugging Face Decision Transformer entries, or {"skipped": reason}.

One module per section (`engine`, `serving`, `store`, `batching`, `stream`, `device`, `cluster`, `failover`, `training`, `alternatives`), what
they share in `harness`, the whole run in `run`, its tables in `report`, the command in `cli`.
"""
