"""Helpers for tests with real Zenoh sessions on loopback (random free ports, no multicast scouting)."""

import json
import socket
import subprocess
import sys
import time


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def config(mode: str = "peer", listen=None, connect=None):
    from services.zconfig import make_config

    return make_config(None, mode=mode, listen=listen, connect=connect,
                       default_role="client" if connect and not listen else "server")


def cristal(*args, env=None, **kw) -> subprocess.Popen:
    """A ``cristal`` subprocess (stdout/stderr to pipes); the caller kills it."""
    import os

    e = dict(os.environ, OMP_WAIT_POLICY="PASSIVE", OMP_NUM_THREADS="1", CRISTAL_PROGRESS="0", **(env or {}))
    return subprocess.Popen([sys.executable, "-m", "services.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=e, **kw)


def stop(p: subprocess.Popen, kill: bool = False, timeout: float = 10.0) -> tuple[str, str]:
    if p.poll() is None:
        p.kill() if kill else p.terminate()
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
    return out, err


def wait_until(pred, timeout: float = 10.0, step: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return False


def summary(stdout: str) -> dict:
    return json.loads(stdout.strip().splitlines()[-1])
