"""node_base lists the package's node modules (for the misspelt params-file section hint) from
the files of ar_tracking/nodes, without importing the nodes package (issue 21: ros sits below
nodes)."""
import subprocess
import sys
import types
from pathlib import Path

import ar_tracking
from ar_tracking.ros import node_base
from ar_tracking.ros.graph_plan import GRAPH_NODES


def test_known_node_names_are_the_node_modules() -> None:
    names = node_base._known_node_names()
    files = sorted(p.stem for p in (Path(ar_tracking.__file__).parent / 'nodes').glob('*.py') if p.stem != '__init__')
    assert names == files
    assert set(GRAPH_NODES) | {'bag_replay', 'camera_replay', 'foxglove_bridge'} <= set(names)


def test_listing_does_not_import_the_nodes_package() -> None:
    code = ('import sys; from ar_tracking.ros import node_base; names = node_base._known_node_names(); '
            "print(len(names), 'ar_tracking.nodes' in sys.modules)")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True).stdout.split()
    assert int(out[0]) >= 11 and out[1] == 'False', out


class _Node(types.SimpleNamespace):
    def get_fully_qualified_name(self) -> str:
        return '/panorama_mapper'

    def get_name(self) -> str:
        return 'panorama_mapper'

    def has_parameter(self, name: str) -> bool:
        return name == 'edr'


def test_a_section_misspelling_another_node_is_named(tmp_path: Path) -> None:
    params = tmp_path / 'p.yaml'
    params.write_text('imu_magnetomter:\n  ros__parameters:\n    rate: 1.0\n'
                      'panorama_mapper:\n  ros__parameters:\n    edr: true\n')
    warnings = node_base.params_file_warnings(_Node(), [str(params)])  # type: ignore[arg-type]
    assert warnings == [f"{params}: section 'imu_magnetomter' names no node; did you mean 'imu_magnetometer'? (ignored)"]
