"""The Kubernetes manifests (deploy/k8s) hang together and route as cluster/nginx.conf does: selectors match their
pods, Services name ports that exist, the gmt Deployment is ready on /readyz and reaches the store through every
sentinel, the sentinels watch it as `gmt cluster up` does, and ingress-nginx hashes on the same session keys.

Validated against the Kubernetes OpenAPI schemas (strict: no unknown field) where `kubernetes-validate` is
installed (`pip install kubernetes-validate`: 100 MB of schemas, so not in the dev extra)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from gmt.cluster import supervisor as cluster

ROOT = Path(__file__).resolve().parents[2]
K8S = ROOT / "deploy" / "k8s"


def _docs() -> list[dict]:
    return [d for f in sorted(K8S.glob("*.yaml")) for d in yaml.safe_load_all(f.read_text()) if d]


def _one(kind: str, name: str) -> dict:
    (doc,) = [d for d in _docs() if d["kind"] == kind and d["metadata"]["name"] == name]
    return doc


def _maps(text: str) -> dict[str, list[tuple[str, str]]]:
    """nginx `map $source $name { pattern value; ... }` blocks: {name: [(pattern, value), ...]}, with $source."""
    out = {}
    for src, name, body in re.findall(r"map \$(\S+) \$(\S+) \{(.*?)\}", text, flags=re.S):
        out[name] = [("source", src), *(tuple(line.split()) for line in body.strip().splitlines())]
    return out


def test_workloads_and_services_select_what_exists():
    docs = _docs()
    workloads = [d for d in docs if d["kind"] in ("Deployment", "StatefulSet")]
    assert {d["metadata"]["name"] for d in workloads} == {"gmt", "redis", "sentinel"}
    for w in workloads:
        labels = w["spec"]["template"]["metadata"]["labels"]
        assert w["spec"]["selector"]["matchLabels"].items() <= labels.items(), w["metadata"]["name"]
        if w["kind"] == "StatefulSet":
            assert (
                _one("Service", w["spec"]["serviceName"])["spec"]["clusterIP"] == "None"
            )  # stable DNS names
    for svc in (d for d in docs if d["kind"] == "Service"):
        (pods,) = [
            w
            for w in workloads
            if svc["spec"]["selector"].items() <= w["spec"]["template"]["metadata"]["labels"].items()
        ]
        names = {p["name"] for c in pods["spec"]["template"]["spec"]["containers"] for p in c["ports"]}
        assert {p["targetPort"] for p in svc["spec"]["ports"]} <= names, svc["metadata"]["name"]


def test_gmt_is_ready_on_readyz_and_reaches_every_sentinel():
    gmt = _one("Deployment", "gmt")
    pod = gmt["spec"]["template"]["spec"]
    (c,) = pod["containers"]
    assert gmt["spec"]["replicas"] == 2 and pod["securityContext"]["runAsNonRoot"]
    assert c["readinessProbe"]["httpGet"] == {"path": "/readyz", "port": 8000}  # the image's GMT_REST_PORT
    assert {p["containerPort"] for p in c["ports"]} == {8000, 50051}
    env = {e["name"]: e for e in c["env"]}
    assert env["GMT_REPLICA_ID"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.name"
    assert env["GMT_AUTH_TOKEN"]["valueFrom"]["secretKeyRef"] == {"name": "gmt-auth", "key": "token"}
    assert env["GMT_STORE_MIN_REPLICAS"]["value"] == "1"
    sentinels = _one("StatefulSet", "sentinel")
    hosts = ",".join(f"sentinel-{i}.sentinel:26379" for i in range(sentinels["spec"]["replicas"]))
    assert env["GMT_REDIS_URL"]["value"] == f"redis+sentinel://{hosts}/{cluster.SENTINEL_SERVICE}"


def test_the_store_is_watched_as_gmt_cluster_up_watches_it():
    assert _one("StatefulSet", "redis")["spec"]["replicas"] == len(cluster.REDIS_NODES)
    assert _one("StatefulSet", "sentinel")["spec"]["replicas"] == len(cluster.SENTINELS)
    scripts = _one("ConfigMap", "gmt-redis")["data"]
    sentinel = scripts["sentinel.sh"]
    assert (
        f"sentinel monitor {cluster.SENTINEL_SERVICE} redis-0.redis 6379 {cluster.SENTINEL_QUORUM}"
        in sentinel
    )
    assert f"down-after-milliseconds gmt {cluster.SENTINEL_DOWN_AFTER_MS}" in sentinel
    assert f"failover-timeout gmt {cluster.SENTINEL_FAILOVER_TIMEOUT_MS}" in sentinel
    # A Redis server asks the sentinels for the primary before it starts, and keeps an AOF.
    assert "get-master-addr-by-name gmt" in scripts["redis.sh"] and "--appendonly yes" in scripts["redis.sh"]


def test_ingress_nginx_hashes_on_docker_nginx_conf_keys():
    snippet = _maps(_one("ConfigMap", "ingress-nginx-controller")["data"]["http-snippet"])
    shipped = _maps(cluster.NGINX_TEMPLATE.read_text())
    assert snippet == shipped and set(shipped) == {"rest_session", "rest_key", "grpc_key"}
    for name, key in (("gmt-rest", "$rest_key"), ("gmt-grpc", "$grpc_key")):
        ing = _one("Ingress", name)
        assert ing["metadata"]["annotations"]["nginx.ingress.kubernetes.io/upstream-hash-by"] == key
        assert (
            ing["metadata"]["annotations"]["nginx.ingress.kubernetes.io/proxy-next-upstream"]
            == "error timeout"
        )
        (path,) = ing["spec"]["rules"][0]["http"]["paths"]
        port = {"gmt-rest": "http", "gmt-grpc": "grpc"}[name]
        assert path["backend"]["service"] == {"name": "gmt", "port": {"name": port}}


def test_the_manifests_validate_against_the_kubernetes_schemas():
    kv = pytest.importorskip("kubernetes_validate", reason="pip install kubernetes-validate (the schemas)")
    for doc in _docs():
        kv.validate(doc, kv.latest_version(), strict=True)
