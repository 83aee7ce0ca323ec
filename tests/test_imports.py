"""Headset and robot clients import the wire contract and the light modules without torch (or numba)."""

import subprocess
import sys

LIGHT = ["protocol", "services.geometry.se3", "services.geometry.camera", "services.io.sequence",
         "services.io.trajectory", "services.io.atomic", "services.cli",
         "protocol.messages", "protocol.codec", "protocol.keys", "services.zconfig", "services.io.bundle",
         "services.client", "services.client.client", "services.client.fallback", "services.client.stream",
         "services.client.cli",
         "services.localize.pnl", "services.localize.pnl_cli", "services.localize.status", "services.prebuild.stella_map",
         "services.localize.direct", "services.prebuild.patches",
         "services.features.orb"]


def test_light_modules_import_without_torch():
    code = "import sys\n" + "".join(f"import {m}\n" for m in LIGHT) + \
        "bad = [m for m in ('torch', 'numba', 'scipy', 'matplotlib') if m in sys.modules]\nassert not bad, bad\n"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_patch_alignment_runs_in_numpy_where_numba_is_missing():
    """The light client's base install has no numba: alignment then takes the numpy path instead of failing."""
    code = ("import sys\nsys.modules['numba'] = None  # as if not installed\n"
            "from services.prebuild.patches import alignment_backend\nassert alignment_backend(warm=True) == 'numpy'\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_cli_help_is_fast_and_lists_commands():
    out = subprocess.run([sys.executable, "-m", "services.cli", "--help"], check=True, capture_output=True, text=True).stdout
    for cmd in ("demo", "sim", "sim-view", "scan", "eval", "router", "serve", "stream"):
        assert cmd in out
