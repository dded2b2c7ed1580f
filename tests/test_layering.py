"""The package's layering, read from the source (AST) rather than from a running import.

- no import cycle between the parts of ``service`` (its subpackages and its top-level
  modules), nor between its modules, counting every import a module makes, lazy ones inside
  functions included;
- ``service.cli`` (argument parsing, exit codes) is imported only by the commands it runs,
  so the daemon's import closure never contains the CLI;
- the research tools (``research/``) sit on top of the product: nothing in ``service`` or
  ``replay`` imports them.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports (absolute names; relative imports resolved)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = _module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            found.add(module)
            # ``from service.cell import profile`` imports the submodule service.cell.profile
            found.update(f"{module}.{alias.name}" for alias in node.names)
    return found


def _sources(top: str) -> list[Path]:
    return sorted((ROOT / top).rglob("*.py"))


def _part(module: str) -> str | None:
    """The layer a ``service`` module belongs to: ``service.<subpackage>`` or the top-level
    module itself (``service.recording``); ``None`` outside ``service``."""
    parts = module.split(".")
    if parts[0] != "service":
        return None
    return ".".join(parts[:2])


def part_graph() -> dict[str, set[str]]:
    """service part -> the other service parts its modules import."""
    known = {_part(_module_name(p)) for p in _sources("service")}
    graph: dict[str, set[str]] = {part: set() for part in known}
    for path in _sources("service"):
        src = _part(_module_name(path))
        for imported in _imports(path):
            dst = _part(imported)
            if dst in known and dst != src:
                graph[src].add(dst)
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def test_cycle_finder_sees_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycles(graph) == [["a", "b", "c"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_relative_imports_are_resolved(tmp_path):
    assert _module_name(ROOT / "service" / "cell" / "__init__.py") == "service.cell"
    assert "service.cell.profile" in _imports(ROOT / "service" / "cell" / "model.py")


def test_no_import_cycle_between_service_parts():
    graph = part_graph()
    assert {"service.cell", "service.estimators", "service.evaluation", "service.diagnosis"} <= set(graph)
    cycles = find_cycles(graph)
    detail = [
        " <-> ".join(c) + ": " + "; ".join(f"{a} -> {b}" for a in c for b in sorted(graph[a]) if b in c)
        for c in cycles
    ]
    assert not cycles, "import cycles between service parts:\n" + "\n".join(detail)


def test_no_import_cycle_between_service_modules():
    """Within a part too: two modules that need each other share a helper that belongs below both."""
    modules = {_module_name(p): p for p in _sources("service")}
    graph = {name: {m for m in _imports(path) if m in modules and m != name} for name, path in modules.items()}
    assert not find_cycles(graph), f"import cycles between service modules: {find_cycles(graph)}"


def test_only_commands_import_the_cli():
    allowed = {"service.cli", "replay.cli"}
    offenders = []
    for top in ("service", "replay"):
        for path in _sources(top):
            name = _module_name(path)
            if name in allowed or name.startswith("service.commands."):
                continue
            if any(m == "service.cli" or m.startswith("service.cli.") for m in _imports(path)):
                offenders.append(name)
    assert not offenders, f"modules other than the commands import service.cli: {offenders}"


def test_product_never_imports_research():
    offenders = [
        _module_name(path)
        for top in ("service", "replay")
        for path in _sources(top)
        if any(m == "research" or m.startswith("research.") for m in _imports(path))
    ]
    assert not offenders, f"the product imports the research tools: {offenders}"


def test_research_tools_live_outside_the_product():
    """The tools that validate and tune the product are not shipped in it."""
    research_tools = {"validate_pybamm", "clean_twin", "validate", "roundtrip", "nested_tuning",
                      "rest_check", "summary", "unseen_cell", "unseen_ocv_truth"}
    shipped = {p.stem for p in _sources("service")} & research_tools
    assert not shipped, f"research tools inside service/: {sorted(shipped)}"
    assert research_tools <= {p.stem for p in _sources("research")}


def test_parameter_names_are_the_profile_and_payload_fields():
    """One list of the seven parameter names; the profile's parameter point and the Zenoh
    payload spell the same names as fields, in the same order."""
    from service.cell.parameters import PARAMETER_NAMES
    from service.cell.profile import ParameterPoint
    from service.daemon.payloads import CellParams

    assert [f for f in ParameterPoint.model_fields if f not in ("temp_c", "i0_a")] == list(PARAMETER_NAMES)
    payload = list(CellParams.model_fields)
    start = payload.index("cell") + 1
    assert payload[start:start + len(PARAMETER_NAMES)] == list(PARAMETER_NAMES)
