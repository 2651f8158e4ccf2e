"""The code stays clean: ruff (pycodestyle, pyflakes, bugbear; ruff.toml) on the package and the
tests, mypy (setup.cfg) on the algorithm cores, and the cores import no ROS."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_ruff_finds_nothing() -> None:
    result = _run('ruff', 'check', '--no-cache', 'ar_tracking', 'test')
    assert result.returncode == 0, result.stdout + result.stderr


def test_mypy_on_the_cores_finds_nothing() -> None:
    result = _run('mypy', '--no-incremental', 'ar_tracking/core')
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
