"""``cristal demo``, the README's main job: the whole loop on the small simulated site, with real Zenoh sessions.

Build (database + P&L map) → router + server in-process on a free loopback port → the client library
streams frames over its own session → APE, FPS, latency, pose sources, overlay, plots, JSON summary.
Nothing of ours is mocked; the frames are few and tiny (200x150) so that it stays well under a minute.
"""

import contextlib
import io
import json
import os
import signal
import subprocess
import sys

import pytest
from _zenoh import cristal, endpoint, free_port, stop, summary

pytestmark = pytest.mark.timeout(240)

SPACING = ["--db-spacing", "1.5", "--map-spacing", "1.5"]
DEADLINE = ["--deadline", "10000"]  # the loop, not the timing, is under test here (a loaded CI box is slow)


@pytest.fixture(scope="module")
def demo_run(small_site, tmp_path_factory):
    """One in-process ``cristal demo`` over 6 frames of the small site: (out dir, stdout lines, stderr)."""
    from services.cli import main

    out = tmp_path_factory.mktemp("demo") / "out"
    o, e = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
        rc = main(["demo", "--site", str(small_site[0]), "--out", str(out), "--frames", "6", *SPACING, *DEADLINE])
    assert rc == 0, o.getvalue() + e.getvalue()
    return out, o.getvalue().strip().splitlines(), e.getvalue()


def test_demo_runs_the_whole_loop_over_zenoh(demo_run):
    import cv2

    from services.client.stream import sources_path
    from services.io.trajectory import read_tum

    out, lines, err = demo_run
    s = json.loads(lines[-1])  # the last stdout line is the JSON summary
    assert any(line.lstrip().startswith("APE (none)") for line in lines[:-1])
    assert "[4/5] streaming" in err and not any("[4/5]" in line for line in lines)  # logs on stderr only
    assert s["frames"] == 6 and s["simulated"] is False and s["endpoint"].startswith("tcp/127.0.0.1:")
    # poses came over Zenoh from the server (the first frame relocalizes with no prior) and were published
    assert s["server"] >= 5 and s["server"] + s["local"] + s["no_pose"] == 6
    assert s["published"] >= s["server"] and s["local_fallback"] is True
    assert s["ape_none_trans_rmse_m"] < 0.05 and s["ape_none_rot_rmse_deg"] < 1.0
    assert "ape_se3_trans_rmse_m" in s and s["rtt_p50_ms"] > 0 and s["fps"] > 0
    est = read_tum(out / "estimate.txt")
    assert len(est) == s["poses"]
    rows = sources_path(out / "estimate.txt").read_text().splitlines()[1:]
    assert len(rows) == 6 and rows[0].split()[1] == "server" and rows[0].split()[3] == "demo-worker"
    img = cv2.imread(str(out / "overlay.jpg"))
    assert img is not None and img.shape[0] >= 100 and img.shape[1] >= 3 * 150
    assert (out / "plots" / "trajectory.png").stat().st_size > 10_000 and (out / "plots" / "errors.png").is_file()
    assert any(p.name == "map.msg" for p in (out / "client-cache").rglob("*"))  # the P&L bundle came over Zenoh
    # the scan's registration error, measured and sent with the map bundle (a perfect simulated scan: about 1 mm)
    assert 0.0 <= s["scan_sigma_mm"] < 2.0
    assert any(p.name == "scan_accuracy.json" for p in (out / "client-cache").rglob("*"))


def test_keep_server_serves_another_client_and_stops_cleanly_on_ctrl_c(demo_run, small_site, tmp_path):
    """A second run (with simulated odometry) reuses the database and map; with --keep-server a `cristal stream` process
    uses its server; Ctrl-C ends it."""
    import socket

    out, _, _ = demo_run
    port = free_port()
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE", CRISTAL_PROGRESS="0")
    with open(tmp_path / "demo.err", "w") as err:  # a file, not a pipe nobody reads
        p = subprocess.Popen([sys.executable, "-m", "services.cli", "demo", "--site", str(small_site[0]), "--out", str(out),
                              "--frames", "2", "--keep-server", "--port", str(port), "--odometry", *SPACING],
                             stdout=subprocess.PIPE, stderr=err, text=True, env=env)
    try:
        first = []
        for line in p.stdout:
            first.append(line)
            if "keep running" in line:
                break
        assert first and "keep running" in first[-1], "".join(first) + (tmp_path / "demo.err").read_text()
        from services.io.sequence import open_sequence
        from services.io.trajectory import write_tum
        from services.sim.odometry import simulate_odometry

        write_tum(tmp_path / "odo.txt", simulate_odometry(open_sequence(small_site[0] / "seq_00").groundtruth))
        c = cristal("stream", small_site[0] / "seq_00", "--out", tmp_path / "t.txt", "--connect", endpoint(port),
                    "--frames", "3", "--deadline", "5000", "--map", tmp_path / "dl", "--odometry", tmp_path / "odo.txt")
        o, e = c.communicate(timeout=120)
        assert c.returncode == 0, o + e
        assert summary(o)["server"] == 3 and summary(o)["odometry"] is True  # each frame went with the device's motion
        p.send_signal(signal.SIGINT)
        o, _ = p.communicate(timeout=60)
    finally:
        stop(p, kill=True)
    assert p.returncode == 0, (tmp_path / "demo.err").read_text()
    s = summary(o)
    assert s["served_after"]["frames"] >= 5 and s["frames"] == 2  # its own 2 frames + the other client's 3
    assert s["odometry"] == "sim" and s["server"] == 2  # streamed with simulated odometry (VIO) on the wire
    assert s["database_s"] < 10 and s["pnl_map_s"] < 5  # reused, not rebuilt
    with socket.socket() as sock:
        assert sock.connect_ex(("127.0.0.1", port)) != 0  # the router is gone


def test_demo_refuses_a_site_without_sequence(tmp_path, capsys):
    from services.cli import main

    (tmp_path / "site").mkdir()
    assert main(["demo", "--site", str(tmp_path / "site"), "--out", str(tmp_path / "o")]) == 2
    assert "no such sequence" in capsys.readouterr().err
