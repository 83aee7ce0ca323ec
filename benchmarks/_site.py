"""The simulated site every benchmark measures on (generated on first use, then reused), and a site's walk with its truth."""

from pathlib import Path

from services.io.sequence import Sequence, open_sequence
from services.sim.site import config_for, generate_site


def ensure_site(path: str | Path, preset: str = "office", seed: int = 1) -> Path:
    path = Path(path)
    if not (path / "site.json").exists():
        generate_site(config_for(preset, seed=seed), path)
    return path


def walk_with_truth(site: str | Path) -> Sequence:
    """SITE/seq_00, which must have its ground truth (a simulated site): an error that says so otherwise."""
    seq = open_sequence(Path(site) / "seq_00")
    if seq.groundtruth is None:
        raise SystemExit(f"{site}/seq_00 has no groundtruth.txt")
    return seq
