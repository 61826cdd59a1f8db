"""The package's layering: no import cycles between jsr's modules, and no module importing another
module's private (underscore) names. Read from the source with ``ast``: lazy imports inside
functions count too."""

import ast
from pathlib import Path

import jsr

PACKAGE = Path(jsr.__file__).parent


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, list[tuple[str, list[str]]]]:
    """Module name -> the jsr modules it imports, each with the names taken from it."""
    modules = {_module_name(path): path for path in PACKAGE.rglob("*.py")}
    found = {}
    for name, path in modules.items():
        edges = []
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                edges += [(alias.name, []) for alias in node.names if alias.name.startswith("jsr.")]
            elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jsr") and not node.level:
                names = [alias.name for alias in node.names]
                submodules = [f"{node.module}.{n}" for n in names if f"{node.module}.{n}" in modules]
                edges += [(m, []) for m in submodules]
                edges.append((node.module, [n for n in names if f"{node.module}.{n}" not in modules]))
        found[name] = [(target, names) for target, names in edges if target in modules and target != name]
    return found


def test_no_import_cycles():
    graph = {module: {target for target, _ in edges} for module, edges in _imports().items()}
    # Tarjan's strongly connected components: any with two or more modules is a cycle
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph[node]:
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    assert cycles == []


def test_no_module_imports_another_modules_private_names():
    private = [(module, target, name) for module, edges in _imports().items() for target, names in edges
               for name in names if name.startswith("_") and not name.startswith("__")]
    assert private == []
