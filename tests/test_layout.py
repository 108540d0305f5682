"""The package's layout, read from its imports (issue 72): rooms by job, no import circles, a small root, the
measuring harness at most a quarter of the code, `garo_model.py` within 350 lines, and the modules that left the
root still importable under their old paths for one release (a saved config.yml names classes by module path)."""

from __future__ import annotations

import ast
import importlib
import sys
import warnings
from pathlib import Path
from typing import Dict, List, Set

import pytest
import yaml

import garo_ns

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "garo_ns"
DATA = Path(__file__).parent / "data"


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> Dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _imports(name: str, path: Path, known: Set[str]) -> Set[str]:
    """The package's modules that `name` imports anywhere in its body (a function's deferred import included)."""
    found: Set[str] = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        found.update(t for t in targets if t in known and t != name)
    return found


def _graph() -> Dict[str, Set[str]]:
    modules = _modules()
    return {name: _imports(name, path, set(modules)) for name, path in modules.items()}


def _cycles(graph: Dict[str, Set[str]]) -> List[List[str]]:
    """The strongly connected components of more than one node (Tarjan's algorithm, iterative)."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on_stack: Set[str] = set()
    found: List[List[str]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def _room(module: str) -> str:
    """A subpackage's room, or a root module on its own. The commands and the harness are the top floor, the harness
    above the commands: the benchmark trains, scores and times through them (the FPS protocol is `tools.fps`, which
    `garo-eval` and `garo-demo` time with too), and no command imports the harness."""
    parts = module.split(".")
    if len(parts) == 1:
        return "garo_ns"
    if len(parts) == 2 and (PACKAGE / f"{parts[1]}.py").exists():
        return parts[1]
    return parts[1]


def test_no_module_imports_itself_round_a_circle():
    assert _cycles(_graph()) == []


def test_the_rooms_import_downward_only():
    """Between rooms the imports form no circle either: a shared constant or kernel handle lives in the lower room."""
    rooms: Dict[str, Set[str]] = {}
    for module, targets in _graph().items():
        room = _room(module)
        rooms.setdefault(room, set()).update(_room(t) for t in targets if _room(t) not in (room, "garo_ns"))
    assert _cycles(rooms) == []
    assert rooms["ops"] == set(), "ops is the lowest room"


def test_the_root_holds_the_plugins_face_only():
    root = sorted(p.name for p in PACKAGE.glob("*.py") if p.name != "__init__.py")
    assert len(root) <= 8, root
    assert {"config.py", "garo_model.py", "garo_strategy.py", "deformation.py", "compat.py", "errors.py"} <= set(root)


def test_every_room_says_what_it_does():
    for room in sorted(p for p in PACKAGE.iterdir() if (p / "__init__.py").exists()):
        doc = ast.get_docstring(ast.parse((room / "__init__.py").read_text()))
        assert doc and len(doc) > 40, f"{room.name}/__init__.py needs a docstring saying what the room does"


def _lines(paths) -> int:
    return sum(len(p.read_text().splitlines()) for p in paths)


def test_the_harness_is_at_most_a_quarter_of_the_code():
    harness = _lines((PACKAGE / "bench").glob("*.py")) + _lines(
        p for p in (ROOT / "benchmarks").iterdir() if p.suffix in (".py", ".sh")
    )
    code = _lines(PACKAGE.rglob("*.py")) + _lines(ROOT.glob("benchmarks/*.py")) + _lines(ROOT.glob("benchmarks/*.sh"))
    code += _lines(ROOT.glob("scripts/*.sh")) + _lines(ROOT.glob("scripts/*.py"))
    assert harness <= 0.25 * code, f"harness {harness} of {code} lines ({harness / code:.1%})"


def test_the_model_module_stays_short():
    assert len((PACKAGE / "garo_model.py").read_text().splitlines()) <= 350


@pytest.fixture
def fresh_old_paths():
    """Forget the old paths' aliases, so that importing one runs the finder (and warns) again."""

    def forget() -> None:
        for old in garo_ns.MOVED:
            sys.modules.pop(old, None)
            garo_ns.__dict__.pop(old.rpartition(".")[2], None)

    forget()
    yield
    forget()


@pytest.mark.parametrize("old", sorted(garo_ns.MOVED))
def test_an_old_module_path_imports_the_moved_module_with_one_warning(old, fresh_old_paths):
    new = importlib.import_module(garo_ns.MOVED[old])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        alias = importlib.import_module(old)
        importlib.import_module(old)  # a second import is the cached alias: no second warning
    deprecations = [w for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(deprecations) == 1 and garo_ns.MOVED[old] in str(deprecations[0].message)
    public = [name for name in vars(new) if not name.startswith("_")]
    assert public and all(getattr(alias, name) is getattr(new, name) for name in public)


def test_a_config_yml_written_before_the_move_still_loads(fresh_old_paths):
    """The classes a config.yml names (the model config, the dataparser, the optimizer config) stayed where they
    were, so it loads without a warning; a tag naming a moved module loads through its alias, with one warning."""
    from garo_ns.config import AdamConfig
    from garo_ns.data.dnerf import GaroDNeRFDataParserConfig
    from garo_ns.garo_model import GaroModel, GaroModelConfig

    text = (DATA / "config_before_rooms.yml").read_text()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trainer = yaml.load(text, Loader=yaml.Loader)
    assert not [w for w in caught if issubclass(w.category, DeprecationWarning) and "garo_ns" in str(w.message)]
    model = trainer.pipeline.model
    assert isinstance(model, GaroModelConfig) and model._target is GaroModel and model.compact
    assert isinstance(trainer.pipeline.datamanager.dataparser, GaroDNeRFDataParserConfig)
    assert isinstance(trainer.optimizers["means"]["optimizer"], AdamConfig)

    from garo_ns.engine.adam import LeanAdam

    old_tag = text + "\nlegacy_optimizer: !!python/name:garo_ns.adam.LeanAdam ''\n"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = yaml.load(old_tag, Loader=yaml.Loader)
    assert len([w for w in caught if issubclass(w.category, DeprecationWarning) and "garo_ns" in str(w.message)]) == 1
    assert loaded.legacy_optimizer is LeanAdam
