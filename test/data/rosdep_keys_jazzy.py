"""Writes rosdep_keys_jazzy.txt: the rosdep keys that resolve on ROS 2 Jazzy / Ubuntu noble.

    python test/data/rosdep_keys_jazzy.py PATH/TO/rosdistro > test/data/rosdep_keys_jazzy.txt

From a checkout of github.com/ros/rosdistro: every released package of jazzy/distribution.yaml
and every key of rosdep/base.yaml and rosdep/python.yaml with an Ubuntu (noble) rule. The test
test/test_package_xml.py checks package.xml against that list without the network.
"""
import subprocess
import sys
from pathlib import Path

import yaml


def main(root: str) -> None:
    root_path = Path(root)
    dist = yaml.safe_load((root_path / 'jazzy' / 'distribution.yaml').read_text())
    packages = set()
    for name, repo in dist['repositories'].items():
        release = repo.get('release')
        if release:
            packages.update(release.get('packages', [name]))
    keys = set()
    for f in ('base.yaml', 'python.yaml'):
        for key, rule in yaml.safe_load((root_path / 'rosdep' / f).read_text()).items():
            ubuntu = rule.get('ubuntu') if isinstance(rule, dict) else None
            if ubuntu is None or (isinstance(ubuntu, dict) and 'noble' in ubuntu and ubuntu['noble'] is None):
                continue
            keys.add(key)
    try:
        commit = subprocess.run(['git', '-C', root, 'log', '-1', '--format=%h %cs'], capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = 'unknown'
    print(f'# rosdep keys resolving on ROS 2 Jazzy / Ubuntu noble (ros/rosdistro {commit}); made by rosdep_keys_jazzy.py')
    for key in sorted(packages | keys):
        print(key)


if __name__ == '__main__':
    main(sys.argv[1])
