"""The committed gRPC stubs are exactly what `make proto` generates from policy.proto and admin.proto."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROTO = ROOT / "proto"


def test_generated_stubs_are_current(tmp_path):
    subprocess.run(
        [
            sys.executable,
            "-m",
            "grpc_tools.protoc",
            f"-I{PROTO}",
            f"--python_out={tmp_path}",
            f"--grpc_python_out={tmp_path}",
            f"--pyi_out={tmp_path}",
            "gmt/v1/policy.proto",
            "gmt/v1/admin.proto",
        ],
        check=True,
    )
    for name in [f"{p}_pb2{s}" for p in ("policy", "admin") for s in (".py", "_grpc.py", ".pyi")]:
        fresh = (tmp_path / "gmt/v1" / name).read_text()
        committed = (PROTO / "gmt/v1" / name).read_text()
        assert fresh == committed, f"proto/gmt/v1/{name} is stale: run `make proto`"


def test_stubs_import_as_package():
    from gmt.v1 import policy_pb2, policy_pb2_grpc

    req = policy_pb2.ActRequest(session_id="s", values=policy_pb2.FloatVector(values=[1.0, 2.0]))
    assert req.WhichOneof("observation") == "values"
    assert hasattr(policy_pb2_grpc, "PolicyServiceStub")
