"""The simulated site every benchmark measures on (generated on first use, then reused)."""

from pathlib import Path

from services.sim.site import config_for, generate_site


def ensure_site(path: str | Path, preset: str = "office", seed: int = 1) -> Path:
    path = Path(path)
    if not (path / "site.json").exists():
        generate_site(config_for(preset, seed=seed), path)
    return path
