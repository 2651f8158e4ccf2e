"""The code stays clean: ruff (pycodestyle, pyflakes, bugbear; ruff.toml) on the package and the
tests, mypy (setup.cfg) on the algorithm cores, and the cores import no ROS."""
from __future__ import annotations

import ast
import hashlib
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_ruff_finds_nothing() -> None:
    result = _run('ruff', 'check', '--no-cache', 'ar_tracking', 'test')
    assert result.returncode == 0, result.stdout + result.stderr


def test_mypy_on_the_cores_finds_nothing() -> None:
    """mypy incremental, its cache outside the checkout (one per checkout path, in the temp
    directory): a repeated run re-checks what changed and what depends on it, and reports the
    errors of unchanged modules again (~0.4 s instead of ~25 s here); the first run is a full
    check."""
    cache = Path(tempfile.gettempdir()) / f'ar_tracking-mypy-{hashlib.sha1(str(ROOT).encode()).hexdigest()[:12]}'
    result = _run('mypy', '--cache-dir', str(cache), 'ar_tracking/core')
    assert result.returncode == 0, result.stdout[-5000:] + result.stderr


def test_the_cores_import_nothing_from_ros_io_eval_sim_or_nodes() -> None:
    banned = ('rclpy', 'ar_tracking.ros', 'ar_tracking.io', 'ar_tracking.eval', 'ar_tracking.sim', 'ar_tracking.nodes')
    offenders = []
    for path in (ROOT / 'ar_tracking' / 'core').rglob('*.py'):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative: resolve against the module's package
                    package = path.relative_to(ROOT).with_suffix('').parts[:-node.level]
                    names = ['.'.join(package + ((node.module,) if node.module else ()))]
                else:
                    names = [node.module or '']
            offenders += [f'{path.relative_to(ROOT)}: {n}' for n in names if n.startswith(banned)]
    assert not offenders, offenders


PACKAGE = ROOT / 'ar_tracking'
#: Issue 21: a module longer than this is split (tests are not counted).
MAX_MODULE_LINES = 600


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package (packages by __init__)."""
    modules = {}
    for path in PACKAGE.rglob('*.py'):
        parts = path.relative_to(ROOT).with_suffix('').parts
        modules['.'.join(parts[:-1] if parts[-1] == '__init__' else parts)] = path
    return modules


def _imported(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package modules that module ``name`` imports anywhere (function-level imports
    included: a lazy import still ties the two modules together), relative imports resolved;
    ``from pkg import sub`` counts both the package and the submodule."""
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')[:len(package.split('.')) - (node.level - 1)]
                module = '.'.join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ''
            targets = [module] + [f'{module}.{a.name}' for a in node.names]
        found.update(t for t in targets if t in modules and t != name)
    return found


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (its modules in order, the first repeated at the end), or None:
    depth-first search, a back edge to a module still on the stack closes a cycle."""
    on_stack: list[str] = []
    state: dict[str, int] = {}  # 1: on the stack, 2: done

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        on_stack.append(module)
        for target in sorted(graph.get(module, ())):
            if state.get(target) == 1:
                return on_stack[on_stack.index(target):] + [target]
            if target not in state:
                cycle = visit(target)
                if cycle:
                    return cycle
        on_stack.pop()
        state[module] = 2
        return None

    for module in sorted(graph):
        if module not in state:
            cycle = visit(module)
            if cycle:
                return cycle
    return None


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert _find_cycle({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == ['a', 'b', 'c', 'a']
    assert _find_cycle({'a': {'b', 'c'}, 'b': {'c'}, 'c': set()}) is None


def test_no_import_cycle_among_the_package_modules() -> None:
    modules = _modules()
    graph = {name: _imported(name, path, modules) for name, path in modules.items()}
    assert sum(map(len, graph.values())) > 100  # the parser sees the imports at all
    cycle = _find_cycle(graph)
    assert cycle is None, ' -> '.join(cycle or [])


def test_no_module_over_600_lines() -> None:
    lengths = {str(p.relative_to(ROOT)): len(p.read_text().splitlines()) for p in PACKAGE.rglob('*.py')}
    assert max(lengths.values()) > 300  # the files were read
    too_long = {p: n for p, n in sorted(lengths.items()) if n > MAX_MODULE_LINES}
    assert not too_long, too_long


def test_every_error_class_derives_from_ArTrackingError() -> None:
    """One error family (ar_tracking/errors.py): each ``class XError`` of the package has
    ArTrackingError or another of the package's error classes among its bases."""
    classes: dict[str, list[str]] = {}
    for path in PACKAGE.rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.ClassDef) and node.name.endswith('Error'):
                bases = [b.id if isinstance(b, ast.Name) else b.attr if isinstance(b, ast.Attribute) else '' for b in node.bases]
                classes[f'{path.relative_to(ROOT)}:{node.name}'] = bases
    names = {key.rpartition(':')[2] for key in classes}
    assert 'ArTrackingError' in names and len(names) > 10
    outside = [key for key, bases in classes.items()
               if not key.endswith(':ArTrackingError') and not any(b in names for b in bases)]
    assert not outside, outside


def test_io_and_ros_import_nothing_from_eval_sim_or_nodes() -> None:
    """The layers below the tools: io and ros never reach up into eval, sim or nodes (the
    runner names its nodes as "module:Class" strings and loads them when it runs)."""
    known: set[str] = set()
    modules = _modules()
    banned = ('ar_tracking.eval', 'ar_tracking.sim', 'ar_tracking.nodes')
    offenders = {f'{name} -> {target}' for name, path in modules.items()
                 if name.startswith(('ar_tracking.io', 'ar_tracking.ros'))
                 for target in _imported(name, path, modules) if target.startswith(banned)}
    assert offenders <= known, sorted(offenders - known)
