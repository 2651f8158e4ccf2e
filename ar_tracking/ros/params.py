"""Parameter files: the packaged config/<node>.yaml defaults and user params files (ROS 2 format).

A params file maps node names (or ``/**`` for every node) to ``ros__parameters``. Values are
turned into rclpy ``Parameter`` overrides for in-process nodes; numbers written as integers
where a node declares floats are accepted (TrackingNode coerces them), in a list too, alone or
mixed with floats.
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from ..errors import ArTrackingError


class ParamsError(ArTrackingError):
    """A params file cannot be read: one line for the user."""


def packaged_config(node_name: str) -> Path | None:
    """Path of config/<node>.yaml: installed with the package (pip), in the source checkout
    (editable install, tests), or in the ROS share directory (colcon); None if there is none."""
    candidates: list[Path] = []
    try:
        candidates.append(Path(str(resources.files('ar_tracking.config'))))
    except ModuleNotFoundError:
        pass
    candidates.append(Path(__file__).resolve().parents[2] / 'config')
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory('ar_tracking')) / 'config')
    except Exception:  # no ament index on a pip install
        pass
    for folder in candidates:
        path = folder / f'{node_name}.yaml'
        if path.is_file():
            return path
    return None


def load_params_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """node name -> {parameter: value} from one ROS 2 params file."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError as exc:
        raise ParamsError(f'{path}: no such params file') from exc
    except (OSError, yaml.YAMLError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ParamsError(f'{path}: not a YAML params file ({first})') from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ParamsError(f'{path}: a params file maps node names to ros__parameters')
    out: dict[str, dict[str, Any]] = {}
    for node, body in data.items():
        if not isinstance(body, dict) or not isinstance(body.get('ros__parameters', {}), dict):
            raise ParamsError(f'{path}: {node} has no ros__parameters mapping')
        stray = [str(k) for k in body if k != 'ros__parameters']
        if stray:
            # The shorthand `node: {name: value}` is ignored by ROS 2 (and was here, silently).
            raise ParamsError(f'{path}: {node}: {", ".join(stray)} must go under ros__parameters '
                              f'({node}: {{ros__parameters: {{{stray[0]}: ...}}}})')
        out[str(node).lstrip('/')] = dict(body.get('ros__parameters') or {})
    return out


def params_for_node(node_name: str, files: list[str | Path], use_packaged: bool = True,
                    namespace: str = '') -> dict[str, Any]:
    """Merged parameters of one node: packaged config first, then each file in order (in each
    file ``/**``, then the node's name, then its namespaced name ``/<namespace>/<node>``)."""
    merged: dict[str, Any] = {}
    sources: list[str | Path] = []
    packaged = packaged_config(node_name) if use_packaged else None
    if packaged is not None:
        sources.append(packaged)
    sources.extend(files)
    for src in sources:
        table = load_params_file(src)
        ns = namespace.strip('/')
        for key in ('**', node_name) + ((f'{ns}/{node_name}',) if ns else ()):
            merged.update(table.get(key, {}))
    return merged


def is_number_list(value: Any) -> bool:
    """Whether ``value`` is a list or tuple of ints and floats (bools excluded)."""
    return isinstance(value, (list, tuple)) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)


def _uniform(value: Any) -> Any:
    """A list that mixes integers and floats (``[1.0, 0, 0]``, as people write a matrix) as floats:
    rclpy takes a list of one type only and would refuse the node's start."""
    if isinstance(value, list) and any(isinstance(v, float) for v in value) and is_number_list(value):
        return [float(v) for v in value]
    return value


def to_overrides(params: dict[str, Any]) -> list[Any]:
    """rclpy Parameter objects for ``parameter_overrides``."""
    from rclpy.parameter import Parameter

    return [Parameter(name, value=_uniform(value)) for name, value in params.items()]
