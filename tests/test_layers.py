"""Imports point down: data and simulation < policies < environments, evaluation and CLI.

Every ``import`` statement of the package (top-level and inside functions) is read from the
source, so a lazy import that goes up is caught too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

BOTTOM, POLICIES, TOP = 0, 1, 2
TOP_MODULES = (
    "tbsim_env.env",
    "tbsim_env.evaluation",
    "tbsim_env.cli",
    "tbsim_env.cli_configs",
    "tbsim_env.distributed",
    "tbsim_env.rendering",
    "tbsim_env.integrations",
    "tbsim_env.benchmark",
    "tbsim_env.__main__",
)
"""Modules (and packages) above the policies; the rest of ``tbsim_env`` is below them."""


def layer(module: str) -> int | None:
    """The layer of a module of the project (None: not the project's)."""
    if module == "policies" or module.startswith("policies."):
        return POLICIES
    if module == "tbsim_env":
        return TOP  # the package's __init__ exposes the environments
    if module.startswith("tbsim_env."):
        top = any(module == m or module.startswith(m + ".") for m in TOP_MODULES)
        return TOP if top else BOTTOM
    return None


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports(path: Path, package: str | None = None) -> list[tuple[int, str]]:
    """(line, imported module) of every import of the file, relative ones resolved against
    ``package`` (by default the file's own)."""
    tree = ast.parse(path.read_text(), str(path))
    if package is None:
        own = module_name(path)
        package = own if path.name == "__init__.py" else own.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            names = [f"{base}.{a.name}" if a.name != "*" else base for a in node.names]
            out += [(node.lineno, n) for n in names]
    return out


def sources() -> list[Path]:
    return sorted([*ROOT.glob("tbsim_env/**/*.py"), *ROOT.glob("policies/**/*.py")])


def resolve(name: str) -> str:
    """``name`` as a module of the project when ``a.b.c`` imports a name ``c`` of ``a.b``."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        candidate = ROOT.joinpath(*parts[:n])
        if candidate.with_suffix(".py").exists() or (candidate / "__init__.py").exists():
            return ".".join(parts[:n])
    return name


def test_no_module_imports_a_layer_above_its_own():
    wrong = []
    for path in sources():
        mine = layer(module_name(path))
        for line, name in imports(path):
            theirs = layer(resolve(name))
            if theirs is not None and mine is not None and theirs > mine:
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not wrong, "imports that point up:\n" + "\n".join(wrong)


@pytest.mark.parametrize(
    "module, expected",
    [
        ("tbsim_env.sim.core", BOTTOM),
        ("tbsim_env.metrics.wosac.scoring", BOTTOM),
        ("policies.trafficbots.model", POLICIES),
        ("tbsim_env.env.episode", TOP),
        ("tbsim_env.rendering.viewer", TOP),
        ("numpy", None),
    ],
)
def test_layers_are_assigned(module, expected):
    assert layer(module) == expected


def test_the_walk_sees_lazy_and_relative_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def f():\n    from policies import make_policy\n    from ..env import episode\n")
    found = [n for _, n in imports(f, package="tbsim_env.sim")]
    assert found == ["policies.make_policy", "tbsim_env.env.episode"]
    assert layer(resolve(found[1])) == TOP
