"""The import layering of ``src/poseflow``: every import between packages is allowed by LAYERS.

``LAYERS`` is the table of docs/ARCHITECTURE.md ("Packages and what each may import"), written
once here; a test below checks that the document's table says the same. Every ``import`` and
``from … import`` counts, at module level or inside a function, relative or absolute, and so does
``importlib.import_module`` with a constant name.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / "src"
DOC = REPO / "docs" / "ARCHITECTURE.md"

#: What each package of poseflow may import, from the ground floor up. A package may always import
#: its own modules, the ``poseflow`` package itself (``__version__``), ``errors`` and the top-level
#: private modules (``_checks``, ``_masks``, ...); those shared modules import only each other.
_BELOW_BASELINES = (
    "geometry",
    "registration",
    "render",
    "data",
    "features",
    "fusion",
    "flows",
    "eval",
    "verify",
    "detect",
)
LAYERS: dict[str, tuple[str, ...]] = {
    "geometry": (),
    "registration": ("geometry",),
    "render": ("geometry",),
    "data": ("geometry", "render"),
    "features": ("geometry", "render", "data"),
    "fusion": (),
    "flows": ("geometry",),
    "eval": ("geometry", "render", "data"),
    "verify": ("geometry", "render", "data", "registration"),
    "detect": ("geometry", "render", "data", "features"),
    "baselines": _BELOW_BASELINES,
    "models": (*_BELOW_BASELINES, "baselines"),
    "assets": (),
    "cli": (*_BELOW_BASELINES, "baselines", "models", "assets"),
}

ROOT = "poseflow"  # the package itself: its __init__ is a lazy namespace


def _is_shared(name: str) -> bool:
    return name == "errors" or name.startswith("_")


@dataclass(frozen=True)
class Arrow:
    """One import between two parts of the package, with where it is written."""

    path: Path
    line: int
    source: str
    target: str
    statement: str


def _parts(src_root: Path) -> set[str]:
    """The top-level packages and modules of ``src_root / "poseflow"``."""
    package = src_root / ROOT
    names = {p.name for p in package.iterdir() if (p / "__init__.py").is_file()}
    names |= {p.stem for p in package.glob("*.py") if p.stem != "__init__"}
    return names


def _source_part(path: Path, src_root: Path) -> str:
    rel = path.relative_to(src_root / ROOT).with_suffix("").parts
    return ROOT if rel == ("__init__",) else rel[0]


def _targets(node: ast.AST, path: Path, src_root: Path, parts: set[str]) -> list[str]:
    """The poseflow modules ``node`` imports, as dotted names (empty for other nodes)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if isinstance(node, ast.ImportFrom):
        if node.level:
            package = list(path.relative_to(src_root).parent.parts)
            base = package[: len(package) - node.level + 1]
            module = ".".join(base + ([node.module] if node.module else []))
        else:
            module = node.module or ""
        if module == ROOT:  # `from poseflow import fusion` imports poseflow.fusion
            return [f"{ROOT}.{a.name}" if a.name in parts else ROOT for a in node.names]
        return [module]
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute | ast.Name)
        and (node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id)
        == "import_module"
        and node.args
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    ):
        return [node.args[0].value]
    return []


def import_arrows(src_root: Path) -> list[Arrow]:
    """Every import from one part of ``src_root/poseflow`` into another, sorted by place."""
    parts = _parts(src_root)
    arrows = []
    for path in sorted((src_root / ROOT).rglob("*.py")):
        source = _source_part(path, src_root)
        text = path.read_text(encoding="utf-8")
        for node in ast.walk(ast.parse(text, filename=str(path))):
            for module in _targets(node, path, src_root, parts):
                dotted = module.split(".")
                if dotted[0] != ROOT:
                    continue
                target = dotted[1] if len(dotted) > 1 else ROOT
                if target != source:
                    statement = ast.get_source_segment(text, node) or module
                    arrows.append(Arrow(path, node.lineno, source, target, statement))
    return sorted(arrows, key=lambda a: (str(a.path), a.line))


def _allowed(source: str, target: str) -> bool:
    if target == ROOT or _is_shared(target):
        return True
    if source == ROOT or _is_shared(source):
        return False
    return target in LAYERS[source]


def violations(src_root: Path) -> list[str]:
    """One message per part missing from LAYERS and per import the table does not allow."""
    unknown = sorted(p for p in _parts(src_root) if not _is_shared(p) and p not in LAYERS)
    problems = [f"poseflow.{p} is not in the layering table (LAYERS)" for p in unknown]
    for a in import_arrows(src_root):
        if a.source in unknown or a.target in unknown or _allowed(a.source, a.target):
            continue
        if a.source in LAYERS:
            may = ", ".join(LAYERS[a.source]) or "no other package"
        else:
            may = "only errors and the private top-level modules"
        where = a.path.relative_to(REPO if REPO in a.path.parents else src_root)
        problems.append(
            f"{where}:{a.line}: {a.source} -> {a.target} (`{a.statement}`); "
            f"{a.source} may import {may}"
        )
    return problems


def test_no_import_crosses_the_layering_table() -> None:
    problems = violations(SRC)
    assert not problems, "imports against the layering table:\n" + "\n".join(problems)


def test_layering_table_names_only_known_packages() -> None:
    for source, allowed in LAYERS.items():
        assert source not in allowed
        assert set(allowed) <= set(LAYERS), source
        # ground floor first: a package imports only packages listed before it
        order = list(LAYERS)
        assert all(order.index(t) < order.index(source) for t in allowed), source


def _doc_table() -> dict[str, set[str]]:
    rows = {}
    for line in DOC.read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        match = re.fullmatch(r"`(\w+)`", cells[0]) if len(cells) == 3 else None
        if match:
            rows[match.group(1)] = set(re.findall(r"`(\w+)`", cells[2]))
    return rows


def test_architecture_doc_mirrors_the_table() -> None:
    doc = _doc_table()
    assert list(doc) == list(LAYERS), "docs/ARCHITECTURE.md lists other packages or order"
    for package, allowed in LAYERS.items():
        assert doc[package] == set(allowed), f"{package}: the doc says {sorted(doc[package])}"


def _write(root: Path, rel: str, text: str) -> None:
    path = root / ROOT / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")


@pytest.fixture
def fake_tree(tmp_path: Path) -> Path:
    _write(tmp_path, "__init__.py", "from poseflow import errors\n")
    _write(tmp_path, "errors.py", "")
    _write(tmp_path, "_checks.py", "from poseflow.errors import PoseflowError\n")
    _write(tmp_path, "geometry/__init__.py", "from poseflow.geometry.se3 import x\n")
    _write(tmp_path, "geometry/se3.py", "import torch\n\nfrom .. import _checks\n")
    _write(tmp_path, "registration/__init__.py", "from ..geometry import se3\n")
    _write(tmp_path, "models/__init__.py", "from poseflow import fusion, __version__\n")
    _write(tmp_path, "fusion/__init__.py", "")
    return tmp_path


def test_checker_accepts_allowed_imports(fake_tree: Path) -> None:
    arrows = {(a.source, a.target) for a in import_arrows(fake_tree)}
    assert arrows == {
        (ROOT, "errors"),
        ("_checks", "errors"),
        ("geometry", "_checks"),
        ("registration", "geometry"),
        ("models", "fusion"),
        ("models", ROOT),
    }
    assert violations(fake_tree) == []


def test_checker_names_file_line_and_arrow(fake_tree: Path) -> None:
    _write(
        fake_tree,
        "fusion/blocks.py",
        '"""Doc."""\n\n\ndef build():\n    from poseflow.models import Net\n\n    return Net\n',
    )
    _write(fake_tree, "geometry/bad.py", "from ..registration import icp\n")
    _write(
        fake_tree, "_masks.py", "import importlib\n\nimportlib.import_module('poseflow.fusion')\n"
    )
    _write(fake_tree, "nets/__init__.py", "")
    problems = violations(fake_tree)
    assert problems[0] == "poseflow.nets is not in the layering table (LAYERS)"
    assert problems[1:] == [
        "poseflow/_masks.py:3: _masks -> fusion (`importlib.import_module('poseflow.fusion')`); "
        "_masks may import only errors and the private top-level modules",
        "poseflow/fusion/blocks.py:5: fusion -> models (`from poseflow.models import Net`); "
        "fusion may import no other package",
        "poseflow/geometry/bad.py:1: geometry -> registration "
        "(`from ..registration import icp`); geometry may import no other package",
    ]
