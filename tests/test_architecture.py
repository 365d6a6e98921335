"""The package's floors (docs/architecture.rst): which room may import which, checked on
the source, lazy imports inside functions included.

A room is a subpackage (``rules``, ``filters``, ...) or a module directly under
``cifilter/``. Data flows one way: a room imports only the rooms beneath it, so the rules
never see a filter, the command line, the network or the Stone Soup adapter.
"""

import ast
from pathlib import Path

import cifilter

ROOT = Path(cifilter.__file__).parent

# room -> the rooms it may import (besides itself). The order of the docs' floor plan.
ALLOWED = {
    "_numerics": set(),
    "result": set(),
    "backend": set(),
    "_progress": set(),
    "registry": {"_numerics", "result"},
    "_kernels": {"_numerics", "backend"},
    "rules": {"_numerics", "_kernels", "registry", "result", "backend"},
    "metrics": {"_numerics"},
    "montecarlo": {"_progress"},
    "filters": {"rules", "registry", "result", "_numerics"},
    "horizon": {"rules", "registry", "result", "_numerics"},
    "network": {"registry", "result", "metrics", "_numerics"},
    "stonesoup": {"registry", "result", "_numerics"},
    "tracking": {"registry", "result", "metrics", "network", "_numerics"},
    "cli": {"rules", "filters", "horizon", "network", "tracking", "registry", "result",
            "backend", "metrics", "montecarlo", "_numerics"},
    "__init__": {"rules", "filters", "horizon", "registry", "result", "backend", "_numerics"},
    "__main__": {"cli"},
}


def room_of(path):
    """The room of a source file: its top-level subpackage or module name."""
    relative = path.relative_to(ROOT)
    return relative.parts[0] if len(relative.parts) > 1 else relative.stem


def imported_rooms(path):
    """The rooms a source file imports, with the line of each import."""
    package = path.relative_to(ROOT.parent).with_suffix("").parts[:-1]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(package[: len(package) - (node.level - 1)])
                module = base + (node.module.split(".") if node.module else [])
                targets = [module + [alias.name] if not node.module else module
                           for alias in node.names]
            elif node.module and node.module.split(".")[0] == "cifilter":
                targets = [node.module.split(".") + [alias.name] for alias in node.names]
        elif isinstance(node, ast.Import):
            targets = [alias.name.split(".") for alias in node.names
                       if alias.name.split(".")[0] == "cifilter"]
        for target in targets:
            if len(target) > 1:
                found.append((target[1], node.lineno))
    return found


def source_files():
    return sorted(ROOT.rglob("*.py"))


def test_every_room_is_in_the_floor_plan():
    rooms = {room_of(path) for path in source_files()}
    assert rooms == set(ALLOWED), rooms.symmetric_difference(ALLOWED)


def test_rooms_import_only_the_floors_beneath_them():
    offences = []
    for path in source_files():
        room = room_of(path)
        for target, line in imported_rooms(path):
            if target != room and target not in ALLOWED[room]:
                offences.append(f"{path.relative_to(ROOT)}:{line}: {room} imports {target}")
    assert not offences, "\n".join(offences)


def test_the_floor_plan_has_no_cycle():
    # a topological order exists: repeatedly remove rooms whose allowed imports are removed
    remaining = {room: set(allowed) for room, allowed in ALLOWED.items()}
    while remaining:
        ready = [room for room, allowed in remaining.items() if not allowed & remaining.keys()]
        assert ready, f"cycle among {sorted(remaining)}"
        for room in ready:
            del remaining[room]


def test_the_rules_never_see_the_upper_floors():
    for upper in ("filters", "cli", "network", "stonesoup", "horizon", "montecarlo",
                  "tracking"):
        assert upper not in ALLOWED["rules"]


def test_the_network_only_generates_data_for_the_tracking_node():
    """The fusion node sits above the network (whose scenarios feed it), never below."""
    assert "tracking" not in ALLOWED["network"]
    assert "network" in ALLOWED["tracking"]
    assert "rules" not in ALLOWED["tracking"]  # the node fuses through the front door


def test_at_most_ten_modules_directly_under_the_package():
    modules = sorted(path.name for path in ROOT.glob("*.py"))
    assert len(modules) <= 10, modules


def test_no_module_imports_another_modules_underscore_names():
    """Shared helpers live in named private modules under public names."""
    offences = []
    for path in source_files():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module is not None and (
                    node.level > 0 or node.module.startswith("cifilter")):
                for alias in node.names:
                    if alias.name.startswith("_"):
                        offences.append(f"{path.relative_to(ROOT)}: {node.module}.{alias.name}")
    assert not offences, "\n".join(offences)
