"""Imports point down, band by band, and no module imports itself through others.

The bands, bottom to top (a module may import its own band and those below it):

| band | modules |
|---|---|
| core | ``core`` (constants, errors, configs, typed command lines, torch helpers) |
| data | ``data`` (readers, the ``Scenario``, preprocessing, the generator) |
| sim | ``sim`` (state, dynamics, collision, off-road, the batched core) |
| observation | ``observation`` (tokens, spec, map nearest neighbours, rows) |
| metrics | ``metrics`` (WOSAC features, scoring, submissions, the WOSAC rollout driver) |
| policies | ``policies`` |
| evaluation | ``evaluation`` (rollouts and scores of a policy) |
| rendering | ``rendering`` (videos, the viewer) |
| env | ``env`` (the environments) |
| top | ``benchmark``, ``distributed``, ``integrations``, ``cli``, the package |

Every ``import`` statement of the package (top-level and inside functions) is read from the
source, so a lazy import that goes up is caught too; ``if TYPE_CHECKING:`` imports count.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

BANDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("core", ("tbsim_env.core",)),
    ("data", ("tbsim_env.data",)),
    ("sim", ("tbsim_env.sim",)),
    ("observation", ("tbsim_env.observation",)),
    ("metrics", ("tbsim_env.metrics",)),
    ("policies", ("policies",)),
    ("evaluation", ("tbsim_env.evaluation",)),
    ("rendering", ("tbsim_env.rendering",)),
    ("env", ("tbsim_env.env",)),
    ("top", ("tbsim_env.benchmark", "tbsim_env.distributed", "tbsim_env.integrations",
             "tbsim_env.cli", "tbsim_env")),
)  # fmt: skip
"""(band, module prefixes), bottom to top."""


def layer(module: str | None) -> int | None:
    """The band index of a module of the project (None: not the project's); the longest
    matching prefix decides (``tbsim_env.env`` before ``tbsim_env``)."""
    if module is None:
        return None
    best: tuple[int, int] | None = None
    for k, (_, prefixes) in enumerate(BANDS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and (
                best is None or len(prefix) > best[1]
            ):
                best = (k, len(prefix))
    return None if best is None else best[0]


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


def test_no_module_imports_a_band_above_its_own():
    wrong = []
    for path in sources():
        mine = layer(module_name(path))
        for line, name in imports(path):
            theirs = layer(resolve(name))
            if theirs is not None and mine is not None and theirs > mine:
                wrong.append(
                    f"{path.relative_to(ROOT)}:{line} ({BANDS[mine][0]}) imports {name} "
                    f"({BANDS[theirs][0]})"
                )
    assert not wrong, "imports that point up:\n" + "\n".join(wrong)


def import_graph() -> dict[str, set[str]]:
    """{module: the project's modules it imports} (packages' own ``__init__`` re-exports
    excluded: a package importing its submodules is no cycle of its own)."""
    graph: dict[str, set[str]] = {}
    for path in sources():
        me = module_name(path)
        deps = {resolve(n) for _, n in imports(path)}
        deps = {d for d in deps if layer(d) is not None and d != me}
        if path.name != "__init__.py":
            deps = {d for d in deps if not me.startswith(d + ".")}  # its own package
        graph[me] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle_between_modules():
    found = [c for c in cycles(import_graph()) if not all(m.endswith("__init__") for m in c)]
    assert not found, "modules that import each other: " + "; ".join(map(str, found))


def test_the_circle_finder_finds_circles():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


@pytest.mark.parametrize(
    "module, band",
    [
        ("tbsim_env.core.constants", "core"),
        ("tbsim_env.data.loader", "data"),
        ("tbsim_env.sim.core", "sim"),
        ("tbsim_env.observation.tokens", "observation"),
        ("tbsim_env.metrics.wosac.scoring", "metrics"),
        ("policies.trafficbots.model", "policies"),
        ("tbsim_env.evaluation", "evaluation"),
        ("tbsim_env.rendering.viewer", "rendering"),
        ("tbsim_env.env.episode", "env"),
        ("tbsim_env.benchmark.runner", "top"),
        ("tbsim_env", "top"),
    ],
)
def test_bands_are_assigned(module, band):
    assert BANDS[layer(module)][0] == band
    assert layer("numpy") is None


def test_the_package_tree_is_the_layer_diagram():
    """Every entry of ``tbsim_env/`` is a band's room (a package, or a module that is a band of
    its own): nothing loose that only the catch-all ``tbsim_env`` prefix would place."""
    rooms = {prefix for _, prefixes in BANDS for prefix in prefixes} - {"tbsim_env"}
    loose = []
    for entry in sorted((ROOT / "tbsim_env").iterdir()):
        if entry.name.startswith(("_", ".")) or entry.suffix not in {".py", ""}:
            continue
        if entry.is_dir() and not (entry / "__init__.py").exists():
            continue
        if f"tbsim_env.{entry.stem}" not in rooms:
            loose.append(entry.name)
    assert not loose, f"modules outside every band's room: {loose}"


def test_the_walk_sees_lazy_and_relative_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def f():\n    from policies import make_policy\n    from ..env import episode\n")
    found = [n for _, n in imports(f, package="tbsim_env.sim")]
    assert found == ["policies.make_policy", "tbsim_env.env.episode"]
    assert BANDS[layer(resolve(found[1]))][0] == "env"
