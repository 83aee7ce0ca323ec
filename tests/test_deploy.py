"""deploy/zenoh/: the access-control router refuses a device another device's keys; TLS with mutual auth works.

Real processes and sessions: ``cristal router`` with the shipped configuration files (paths and port rewritten for
the test), a server and devices connecting with user/password or certificates."""

import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from _zenoh import cristal, endpoint, free_port, stop, wait_until

from protocol import keys
from protocol.codec import decode, encode
from protocol.messages import FrameRequest, Intrinsics, PoseReply, Status

pytestmark = pytest.mark.timeout(120)
DEPLOY = Path(__file__).resolve().parents[1] / "deploy" / "zenoh"
CAM = Intrinsics(width=64, height=48, fx=50, fy=50, cx=31.5, cy=23.5)
JPG = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8))[1].tobytes()


class FixedBackend:
    """A backend that always answers the same pose: these tests are about who may talk to whom."""

    name = "fixed"

    def new_tracker(self):
        from services.geometry.se3 import Pose
        from services.server.backend import TrackResult

        class T:
            def reset(self):
                pass

            def process(self, image, camera, prior, motion, stamp=None, exposure_s=None):
                return TrackResult("tracking", Pose.from_tum([1, 2, 3, 0, 0, 0, 1]), 99, 0.5, 0.01, 0.1, {"total_ms": 1.0})

        return T()

    def site_meta(self):
        return {}


def _cfg_from(path: Path, **patch):
    """A deploy config file, loaded by zenoh itself, with fields overridden for the test."""
    import zenoh

    cfg = zenoh.Config.from_file(str(path))
    for k, v in patch.items():
        cfg.insert_json5(k, json.dumps(v))
    return cfg


def _start_router(tmp_path, name, port, **patch):
    text = (DEPLOY / name).read_text()
    for k, v in patch.items():
        text = text.replace(k, v)
    f = tmp_path / name
    f.write_text(text)
    p = cristal("router", "--zenoh-config", f, "--listen", patch.get("__listen__", endpoint(port)))
    import socket

    def up():
        with socket.socket() as s:
            return s.connect_ex(("127.0.0.1", port)) == 0

    assert wait_until(up, 20), stop(p)
    return p


def _server(cfg):
    from services.server.service import LocalizationServer, ServerConfig

    return LocalizationServer(FixedBackend(), ServerConfig(site="lab", map_id="office", server_id="w0"), cfg).start()


def _frame(client, seq=1):
    return encode(FrameRequest(client=client, seq=seq, image=JPG, intrinsics=CAM))


def test_acl_refuses_another_clients_keys(tmp_path):
    import zenoh

    from services.client.client import LocalizationClient

    port = free_port()
    shutil.copy(DEPLOY / "credentials.txt", tmp_path / "credentials.txt")
    router = _start_router(tmp_path, "router-acl.json5", port,
                           **{'"credentials.txt"': json.dumps(str(tmp_path / "credentials.txt"))})
    sessions, srv = [], None

    def login(user, password):
        s = zenoh.open(_cfg_from(DEPLOY / "client-usrpwd.json5", **{"connect/endpoints": [endpoint(port)],
                                                                       "transport/auth/usrpwd/user": user,
                                                                       "transport/auth/usrpwd/password": password}))
        sessions.append(s)
        return s

    try:
        srv = _server(_cfg_from(DEPLOY / "server.json5", **{"connect/endpoints": [endpoint(port)],
                                                             "transport/auth/usrpwd/user": "server",
                                                             "transport/auth/usrpwd/password": "change-me-server"}))
        fleet_got, d1_got_other = [], []
        fleet = login("fleet", "change-me-fleet")
        fleet.declare_subscriber(keys.poses("lab"), lambda s: fleet_got.append(decode(s.payload.to_bytes(), PoseReply).client))
        d1 = LocalizationClient(session=login("dev-1", "change-me-dev-1"), client_id="dev-1", site="lab", map_id="office",
                                deadline_ms=2000)
        d2 = LocalizationClient(session=login("dev-2", "change-me-dev-2"), client_id="dev-2", site="lab", map_id="office",
                                deadline_ms=2000)
        own = []
        d1.session.declare_subscriber(keys.pose("lab", "office", "dev-1"), lambda s: own.append(1))
        d1.session.declare_subscriber(keys.pose("lab", "office", "dev-2"), lambda s: d1_got_other.append(1))
        assert d1.wait_for_server(10) and d2.wait_for_server(10)  # discovery is allowed
        time.sleep(0.3)
        # own keys: served
        r = d1.request_raw(_frame("dev-1"), "w0", 3.0)
        assert r is not None and r.status is Status.TRACKING and r.client == "dev-1"
        r2 = d2.request_raw(_frame("dev-2"), "w0", 3.0)
        assert r2 is not None and r2.status is Status.TRACKING
        # dev-1 on dev-2's frame key: the router refuses it, the query never reaches a server
        t0 = time.monotonic()
        assert d1.request_raw(_frame("dev-2", 5), "w0", 1.0, client_key="dev-2") is None
        assert srv.counts["frames"] == 2 and srv.counts["rejected"] == 0
        # poses: dev-1 sees its own, never dev-2's; the fleet role sees both
        assert wait_until(lambda: {"dev-1", "dev-2"} <= set(fleet_got), 5), fleet_got
        assert wait_until(lambda: len(own) >= 1, 5)
        time.sleep(0.3)
        assert d1_got_other == []
        assert d1.site_info() is not None  # site info is readable
        # a wrong password does not get in
        with pytest.raises(Exception):
            login("dev-1", "wrong")
        d1.close()
        d2.close()
    finally:
        if srv is not None:
            srv.close()
        for s in sessions:
            s.close()
        stop(router)


def _openssl(*args, cwd):
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def make_certs(d: Path) -> None:
    """A site CA, a router certificate for localhost / 127.0.0.1, and client certificates (the commands of deploy/README.md)."""
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=cristal-site-ca",
             "-keyout", "ca-key.pem", "-out", "ca.pem", cwd=d)
    for name, cn, ext in (("router", "localhost", "subjectAltName=DNS:localhost,IP:127.0.0.1"),
                          ("client", "dev-1", "extendedKeyUsage=clientAuth"),
                          ("server", "gpu-worker-0", "extendedKeyUsage=clientAuth")):
        _openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={cn}", "-keyout", f"{name}-key.pem",
                 "-out", f"{name}.csr", cwd=d)
        (d / f"{name}.ext").write_text(ext + "\n")
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial",
                 "-days", "2", "-out", f"{name}.pem", "-extfile", f"{name}.ext", cwd=d)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")
def test_mutual_tls_router(tmp_path):
    import zenoh

    from services.client.client import LocalizationClient

    make_certs(tmp_path)
    port = free_port()
    ep = f"tls/localhost:{port}"
    router = _start_router(tmp_path, "router-tls.json5", port, **{"/etc/cristal/tls/": str(tmp_path) + "/",
                                                                  "__listen__": f"tls/127.0.0.1:{port}"})
    sessions, srv = [], None

    def tls_cfg(name):
        text = (DEPLOY / "client-tls.json5").read_text().replace("/etc/cristal/tls/", str(tmp_path) + "/")
        text = re.sub(r"client(-key)?\.pem", lambda m: f"{name}{m.group(1) or ''}.pem", text)
        (tmp_path / f"{name}.json5").write_text(text)
        return _cfg_from(tmp_path / f"{name}.json5", **{"connect/endpoints": [ep]})

    try:
        srv = _server(tls_cfg("server"))
        s = zenoh.open(tls_cfg("client"))
        sessions.append(s)
        cl = LocalizationClient(session=s, client_id="dev-1", site="lab", map_id="office", deadline_ms=3000)
        assert cl.wait_for_server(10)
        r = cl.request_raw(_frame("dev-1"), "w0", 3.0)
        assert r is not None and r.status is Status.TRACKING
        cl.close()
        # without a client certificate, mutual TLS refuses the connection
        text = (DEPLOY / "client-tls.json5").read_text().replace("/etc/cristal/tls/", str(tmp_path) + "/")
        text = re.sub(r'\s*connect_(private_key|certificate): "[^"]*",', "", text)
        (tmp_path / "nocert.json5").write_text(text)
        with pytest.raises(Exception):
            sessions.append(zenoh.open(_cfg_from(tmp_path / "nocert.json5", **{"connect/endpoints": [ep]})))
    finally:
        if srv is not None:
            srv.close()
        for x in sessions:
            x.close()
        stop(router)


def _parses(argv):
    from services.cli import build_parser

    args = build_parser().parse_args(argv)
    assert getattr(args, "func", None) is not None, argv
    return args


def test_every_deploy_file_loads_and_its_commands_parse():
    """Zenoh files load in zenoh; the commands in the Dockerfile, systemd units and Kubernetes manifests are valid."""
    import shlex

    import yaml
    import zenoh

    for f in sorted(DEPLOY.glob("*.json5")):
        # and none maps same-host peers' frames through shared memory (kept mapped after they leave: test_zenoh_sessions)
        assert json.loads(zenoh.Config.from_file(str(f)).get_json("transport/shared_memory/enabled")) is False, f
    root = DEPLOY.parent
    docker = (root / "docker" / "Dockerfile").read_text()
    cmd = json.loads(re.search(r"^CMD (\[.*\])$", docker, re.M).group(1))
    assert re.search(r'^ENTRYPOINT \["cristal"\]$', docker, re.M)
    a = _parses(cmd)
    assert a.command == "serve" and a.map_dir == "/data/pnl"
    for unit in sorted((root / "systemd").glob("*.service")):
        line = re.search(r"^ExecStart=(.*)$", unit.read_text(), re.M).group(1).replace("%i", "0")
        argv = shlex.split(line)
        assert argv[0].endswith("/cristal")
        _parses(argv[1:])
    docs = [d for d in yaml.safe_load_all((root / "k8s" / "cristal.yaml").read_text()) if d]
    kinds = {d["kind"] for d in docs}
    assert {"Deployment", "Service", "StatefulSet"} <= kinds
    for d in docs:
        for c in d.get("spec", {}).get("template", {}).get("spec", {}).get("containers", []):
            _parses(c["args"])
    sts = next(d for d in docs if d["kind"] == "StatefulSet")
    assert sts["spec"]["template"]["spec"]["containers"][0]["resources"]["limits"]["nvidia.com/gpu"] == 1


def test_a_zenoh_file_that_leaves_shared_memory_on_is_warned_about(tmp_path, caplog):
    """A site's own --zenoh-config is taken as is, but one that leaves zenoh's shared-memory transport on (its default)
    gets a warning: a long-running server then keeps 16 MiB and an open file per same-host client that left (stop 54).
    The deploy files turn it off and get none."""
    import logging

    from services.zconfig import make_config

    f = tmp_path / "mine.json5"
    f.write_text('{ mode: "peer" }\n')
    with caplog.at_level(logging.WARNING, logger="services.zconfig"):
        make_config(f)
        assert any("shared-memory" in r.getMessage() for r in caplog.records), caplog.text
        caplog.clear()
        for p in sorted((Path(__file__).resolve().parents[1] / "deploy" / "zenoh").glob("*.json5")):
            make_config(p)
        assert not caplog.records, caplog.text
