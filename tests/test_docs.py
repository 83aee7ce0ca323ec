"""The documentation keeps up with the code: every reason a localizer gives for a LOST frame is explained in
docs/TROUBLESHOOTING.md (a reason added without its row fails here)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _reason_texts() -> set[str]:
    """The heads of every ``reason`` the localizers assign or pass: the literal text before its first colon or
    bracket, at most six words."""
    files = [*(ROOT / "services" / "localize").glob("*.py"), ROOT / "services" / "geometry" / "rolling_shutter.py"]
    out = set()
    for path in files:
        values = []
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                if any((isinstance(t, ast.Name) and t.id in ("reason", "unconfirmed", "NOT_UNDONE"))
                       or (isinstance(t, ast.Attribute) and t.attr == "reason") for t in targets):
                    values.append(node.value)
            elif isinstance(node, ast.keyword) and node.arg == "reason":
                values.append(node.value)
            elif isinstance(node, ast.FunctionDef) and node.name in ("_unconfirmed", "_confirm"):
                values += [n.value for n in ast.walk(node) if isinstance(n, ast.Return) and n.value is not None]
        for v in values:
            for c in ast.walk(v):
                text = None
                if isinstance(c, ast.JoinedStr) and c.values and isinstance(c.values[0], ast.Constant):
                    text = c.values[0].value
                elif isinstance(c, ast.Constant) and isinstance(c.value, str):
                    text = c.value
                if text and text[0].islower() and " " in text.strip():  # a sentence's start, not a continuation
                    head = text.split(":")[0].split("(")[0]
                    out.add(" ".join(head.split()[:6]).rstrip(","))
    return out


def test_every_lost_reason_is_explained_in_the_troubleshooting_guide():
    texts = _reason_texts()
    assert len(texts) >= 15, texts  # the scan finds them (R&M, P&L, the runner, the rolling shutter)
    guide = (ROOT / "docs" / "TROUBLESHOOTING.md").read_text()
    missing = sorted(t for t in texts if t not in guide)
    assert not missing, f"reasons not in docs/TROUBLESHOOTING.md: {missing}"
