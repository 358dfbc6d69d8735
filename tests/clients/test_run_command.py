"""`gmt run` end to end: a real server, a HalfCheetah-v5 episode, the table, the files, the errors."""

from __future__ import annotations

import json
import re
import socket
from pathlib import Path

import pytest
from typer.testing import CliRunner

from gmt.common.envs import VIDEO_SIZE
from gmt.service.cli import app

runner = CliRunner()


def test_run_over_grpc_stream_prints_the_table_and_writes_the_files(live_server, tmp_path):
    args = ["run", "--grpc", live_server.grpc_target, "--stream", "--env", "HalfCheetah-v5"]
    args += ["--goal", "1", "--schedule", "low@16", "--steps", "24", "--seed", "2", "--out", str(tmp_path)]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    rows = [line.split()[:4] for line in r.output.splitlines() if line[:1].isdigit()]
    assert rows == [["1", "(medium)", "0-15", "4-15"], ["0", "(low)", "16-23", "18-23"]]
    assert "step     0  goal 1 (medium, target 1.00)" in r.output  # the status line
    doc = json.loads((tmp_path / "episode-0.json").read_text())
    assert doc["transport"] == f"grpc stream {live_server.grpc_target}" and doc["schedule"] == [[16, "low"]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode-0.csv", "episode-0.json", "episode-0.png"]


def test_video_is_an_mp4_with_one_frame_per_step_and_a_strip_of_every_third(live_server, tmp_path):
    imageio = pytest.importorskip("imageio.v2")
    pytest.importorskip("imageio_ffmpeg")
    from PIL import Image

    args = ["run", "--server", live_server.rest_url, "--steps", "8", "--out", str(tmp_path), "--video"]
    r = runner.invoke(app, [*args, "--strip-every", "3"])
    assert r.exit_code == 0, r.output
    video = tmp_path / "episode-0.mp4"
    assert f"wrote {video}" in r.output
    with imageio.get_reader(video) as reader:
        assert reader.count_frames() == 8
        frame = reader.get_data(0)
    width, height = VIDEO_SIZE
    assert frame.shape == (height, width, 3) and frame.std() > 10  # rendered, not blank
    strip = Image.open(tmp_path / "episode-0-strip.png")  # steps 0, 3 and 6, captioned above
    assert strip.size[0] == 3 * width + 2 * 4 and strip.size[1] > height
    assert f"wrote {tmp_path / 'episode-0-strip.png'}" in r.output


def test_mismatched_environment_exits_with_a_message_naming_both(live_server):
    r = runner.invoke(app, ["run", "--server", live_server.rest_url, "--env", "Hopper-v5", "--steps", "5"])
    assert r.exit_code == 1
    assert (
        "error: environment Hopper-v5 does not match model 'tiny-gmt' (trained on HalfCheetah-v5)" in r.output
    )
    assert "Box(float64, shape=[11]) of Hopper-v5 vs Box(float64, shape=[17]) of the model" in r.output


def test_unreachable_server_exits_with_a_clear_message():
    r = runner.invoke(app, ["run", "--server", "http://127.0.0.1:9", "--retries", "1", "--steps", "5"])
    assert r.exit_code == 1
    assert "error: unavailable: could not connect to http://127.0.0.1:9 after 2 attempt(s)" in r.output


@pytest.mark.parametrize("transport", [["--grpc"], ["--grpc", "--stream"], ["--server"]])
def test_refused_connection_is_one_line_naming_the_target_and_what_to_check(transport):
    with socket.socket() as closed:  # bound, never listening: every connection to it is refused
        closed.bind(("127.0.0.1", 0))
        target = f"127.0.0.1:{closed.getsockname()[1]}"
        address = target if transport[0] == "--grpc" else f"http://{target}"
        args = ["run", transport[0], address, *transport[1:], "--retries", "0", "--steps", "5"]
        r = runner.invoke(app, args)
    assert r.exit_code == 1
    server, line = r.output.strip().splitlines()  # the server it acts on, then one line of error
    assert server.startswith("server: ") and server.endswith(address)
    assert line.startswith(f"error: unavailable: could not connect to {address} after 1 attempt(s): ")
    assert "Rpc" not in line and "check that the server is running" in line
    flag = "--grpc HOST:PORT" if transport[0] == "--grpc" else "--server URL"
    assert flag in line


def test_run_is_a_gmt_command():
    r = runner.invoke(app, ["--help"])
    assert r.exit_code == 0 and "run" in r.output and "Drive an agent remotely" in r.output


def test_bad_schedule_and_video_without_out_are_usage_errors():
    r = runner.invoke(app, ["run", "--schedule", "2@x"])
    assert r.exit_code == 2 and "GOAL@STEP" in r.output
    r = runner.invoke(app, ["run", "--video"])
    assert r.exit_code == 2 and "--out" in r.output
    r = runner.invoke(app, ["run", "--stream"])  # the Control stream is gRPC's: it was ignored over REST
    assert r.exit_code == 2 and "--grpc" in r.output
    r = runner.invoke(app, ["run", "--timeout", "0"])  # was "could not connect" to a running server
    assert r.exit_code == 2 and "--timeout" in r.output


def test_addresses_without_scheme_or_port_mean_gmt_serves_defaults():
    from gmt.client.grpc import DEFAULT_PORT, GrpcClient
    from gmt.client.models import AdminClient
    from gmt.client.rest import rest_base_url
    from gmt.service.settings import Settings

    assert DEFAULT_PORT == Settings.model_fields["grpc_port"].default
    with GrpcClient("localhost") as c:  # was gRPC's TLS default, 443
        assert c.target == "localhost:50051"
    with GrpcClient("grpc://127.0.0.1:7") as c:
        assert c.target == "127.0.0.1:7"
    assert rest_base_url("localhost:8000/") == "http://localhost:8000"
    with AdminClient("localhost:8000") as c:  # `gmt models -s localhost:8000` said "unsupported protocol"
        assert str(c.http.base_url) == "http://localhost:8000"


def test_the_documented_gmt_run_examples_write_to_distinct_folders():
    root = Path(__file__).resolve().parents[2]
    text = (root / "README.md").read_text() + (root / "docs" / "clients.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    lines = [c.removeprefix(".venv/bin/") for b in blocks for c in b.replace("\\\n", " ").splitlines()]
    commands = [c for c in lines if c.startswith("gmt run ")]
    outs = [c.split("--out ")[1].split()[0] for c in commands if "--out " in c]
    assert len(commands) >= 3 and len(outs) == len(commands)
    assert len(set(outs)) == len(outs), outs  # one example's files never overwrite another's
