"""Every link and every repository path the documentation names must exist."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = sorted([ROOT / "README.md", ROOT / "hdl" / "README.md", *(ROOT / "docs").rglob("*.md")])
# Top-level folders whose paths the docs cite; generated folders (runs/, .bench/) are not checked.
TRACKED_ROOTS = ("services", "shared", "docs", "deploy", "bench", "tests", "hdl", "learning", "evaluation",
                 "calibration", "perception", "skin", "interop")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
CODE = re.compile(r"`([^`\s]+)`")
PLAIN = re.compile(r"(?<![\w/.])((?:" + "|".join(TRACKED_ROOTS) + r")/[\w./-]*\w)")  # not inside runs/...
DEPLOYMENTS = sorted((ROOT / "deploy").glob("*.toml"))


def _cited_paths(text: str) -> set[str]:
    paths = {m.group(1) for m in LINK.finditer(text) if "://" not in m.group(1)}
    for token in CODE.findall(text):
        token = token.rstrip(".,:;")
        if any(c in token for c in "<>*{}$|") or "/" not in token:
            continue
        if token.split("/")[0] in TRACKED_ROOTS:
            paths.add(token)
    return {p.split("#")[0] for p in paths if p.split("#")[0]}


def _resolves(doc: Path, cited: str) -> bool:
    # Python module paths are written with slashes and may omit ".py"; links are relative to the doc.
    candidates = [ROOT / cited, doc.parent / cited, ROOT / f"{cited}.py"]
    if "." in cited.split("/")[-1] and not cited.endswith((".py", ".md", ".toml")):
        stem = cited.rsplit(".", 1)[0]  # `services/policy/ours.Ours` style: a module and a name in it
        candidates.append(ROOT / f"{stem}.py")
    return any(c.exists() for c in candidates)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_cited_path_exists(doc: Path) -> None:
    missing = sorted(p for p in _cited_paths(doc.read_text()) if not _resolves(doc, p))
    assert not missing, f"{doc.relative_to(ROOT)} cites paths that do not exist: {missing}"


@pytest.mark.parametrize("deployment", DEPLOYMENTS, ids=lambda p: p.name)
def test_deployment_comments_cite_existing_paths(deployment: Path) -> None:
    comments = "\n".join(line.split("#", 1)[1] for line in deployment.read_text().splitlines() if "#" in line)
    missing = sorted(p for p in PLAIN.findall(comments) if not _resolves(deployment, p))
    assert not missing, f"{deployment.name} cites paths that do not exist: {missing}"


def test_the_checker_notices_a_missing_path(tmp_path: Path) -> None:
    doc = tmp_path / "x.md"
    cited = _cited_paths("see `services/policy/nothing_here.py` and [a](docs/policy.md) and `runs/x/y.pt`")
    assert cited == {"services/policy/nothing_here.py", "docs/policy.md"}
    assert not _resolves(doc, "services/policy/nothing_here.py")
    assert _resolves(doc, "docs/policy.md")
