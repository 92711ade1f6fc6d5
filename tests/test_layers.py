"""The package's layers: no module imports from a layer above its own (imports inside functions
count too), so each layer can be used, tested and read without the ones on top of it."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "t3fast"

#: bottom to top; a module may import from its own layer and the ones listed before it
LAYERS = [
    {"errors", "paths", "device", "device_constants", "host_syncs", "io"},
    {"ops"},
    {"data"},
    # the tracker and box fits read the pose geometry of models.ego_motion; T3Former runs the forecast stages
    {"agents", "models", "forecast"},
    {"pretrained"},
    {"evaluation"},
    {"viz"},
    {"training"},
    {"presets"},
    {"commands", "__main__"},
]
LEVEL = {part: level for level, parts in enumerate(LAYERS) for part in parts}


def _part(module: str) -> str | None:
    """``t3fast.training.trainer`` -> ``training``; None for ``t3fast`` itself."""
    names = module.split(".")
    return names[1] if names[0] == "t3fast" and len(names) > 1 else None


def _imports(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names if node.module == "t3fast")
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return found


def test_every_part_of_the_package_has_a_layer():
    parts = {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    parts |= {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    assert parts == set(LEVEL), f"unplaced: {parts - set(LEVEL)}, gone: {set(LEVEL) - parts}"


def test_no_import_reaches_up_a_layer():
    upward = []
    for path in PACKAGE.rglob("*.py"):
        own = _part(".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts))
        if own is None:  # t3fast/__init__.py: the lazy public API may name any layer
            continue
        for module in _imports(path):
            other = _part(module)
            if other in LEVEL and LEVEL[other] > LEVEL[own]:
                upward.append(f"{path.relative_to(PACKAGE.parent)} imports {module}")
    assert not upward, "\n".join(sorted(upward))
