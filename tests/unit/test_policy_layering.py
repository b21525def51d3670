"""The policy's packages by role: the node (services/policy) depends on the model and inference code
only; offline code (learning/, evaluation/) points at it, never back; no import cycles; imports at
module top except matplotlib and LeRobot."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("services/policy", "learning", "evaluation")
FIRST_PARTY = ("services", "learning", "evaluation", "shared", "deploy")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> tuple[set[str], list[tuple[int, str]]]:
    """First-party modules imported at module level, and (line, module) of imports inside functions."""
    tree = ast.parse(path.read_text())
    top, nested = set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        if node.col_offset:
            nested += [(node.lineno, n) for n in names]
        else:
            top |= {n for n in names if n.split(".")[0] in FIRST_PARTY}
    return top, nested


MODULES = {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def resolved(names: set[str]) -> set[str]:
    """Imported names that are modules of these packages (``from a.b import c`` may name module a.b.c)."""
    return {n for n in names if n in MODULES}


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m.startswith("services.policy")))
def test_the_node_imports_the_model_and_inference_code_only(module):
    top, _ = imports(MODULES[module])
    foreign = sorted(n for n in top if not n.startswith(("services.policy", "shared")))
    assert not foreign, f"{module} imports {foreign}"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m.startswith("learning")))
def test_learning_does_not_import_evaluation(module):
    top, _ = imports(MODULES[module])
    assert not [n for n in top if n.startswith("evaluation")]


# Imported where used: matplotlib (plots only), LeRobot (installed beside the venv, put on the path
# by interop/lerobot_site.py for row (8) alone).
LATE_IMPORTS = ("matplotlib", "lerobot")


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_at_module_top_except_matplotlib_and_lerobot(module):
    _, nested = imports(MODULES[module])
    assert all(n.startswith(LATE_IMPORTS) for _, n in nested), f"{module}: {nested}"


def test_no_import_cycles():
    graph = {m: resolved(imports(p)[0]) - {m} for m, p in MODULES.items()}
    state: dict[str, int] = {}  # 1 on the current path, 2 done

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                raise AssertionError("import cycle: " + " -> ".join(path[path.index(n):] + [m, n]))
            if n not in state:
                visit(n, path + [m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])


def test_no_module_over_500_lines():
    paths = [*MODULES.values(), *sorted((ROOT / "tests/unit").glob("test_policy_*.py"))]
    long = {str(p.relative_to(ROOT)): n for p in paths if (n := len(p.read_text().splitlines())) > 500}
    assert not long
