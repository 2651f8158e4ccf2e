"""ar_tracking: an ament_python package that also installs with plain pip.

On a ROS 2 install (colcon) rclpy and the message packages come from the system; on a pip-only
machine the ``ros`` extra brings the ROS 2 Jazzy wheels from PyPI.
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'ar_tracking'

# One console script per node executable (`ros2 run ar_tracking <node>`), plus the CLI.
NODES = [
    'camera_replay',
    'bag_replay',
    'imu_magnetometer',
    'panorama_mapper',
    'hybrid_orientation_filter',
    'annotation_matcher',
    'ar_view',
    'marker_tracker',
    'visual_inertial_filter',
    'keyframe_slam_mapper',
    'foxglove_bridge',
]

setup(
    name=PACKAGE,
    version='0.1.0',
    description='AR tracking on ROS 2: panorama tracking, annotations, keyframe SLAM, marker+IMU fusion',
    packages=find_packages(exclude=['test', 'test.*']) + [f'{PACKAGE}.config'],
    package_dir={f'{PACKAGE}.config': 'config'},
    package_data={f'{PACKAGE}.config': ['*.yaml']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', glob('config/*.yaml')),
        (f'share/{PACKAGE}/launch', glob('launch/*.py')),
    ],
    python_requires='>=3.10',
    install_requires=[
        'numpy>=1.24',
        'scipy>=1.10',
        'opencv-python-headless>=4.8',
        'rosbags>=0.11,<0.12',  # io/bag_typestores.py builds on AnyReader's opening (0.11)
        'mcap>=1.1',
        'gtsam>=4.2',
        'evo>=1.25',
        'matplotlib>=3.7',
        'tqdm>=4.60',
        'PyYAML>=6.0',
        # The AHRS engine of imu_magnetometer (Laidig & Seel 2023; MIT).
        'vqf>=2.0',
        # The shared annotation store on PostgreSQL/PostGIS (io/postgis_store.py).
        'psycopg[binary]>=3.1',
        # The live view: the graph's topics over the Foxglove WebSocket protocol (ros/foxglove.py).
        'foxglove-sdk>=0.30',
    ],
    extras_require={
        # ROS 2 Jazzy from PyPI, for machines without a ROS install.
        'ros': ['ros-jazzy-rclpy[fastrtps]', 'ros-jazzy-common-interfaces'],
        'test': ['pytest>=7', 'pytest-xdist>=3', 'hypothesis>=6', 'websockets>=12', 'ruff>=0.6', 'mypy>=1.10'],
        # Peer estimators compared in `ar-tracking bench` only (never imported at runtime).
        'bench': ['imufusion>=1.2', 'ahrs>=0.3.1'],
    },
    zip_safe=True,
    maintainer='ar_tracking developers',
    maintainer_email='dev@ar-tracking.invalid',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [f'{node} = {PACKAGE}.nodes.{node}:main' for node in NODES]
        + ['ar-tracking = ar_tracking.cli:main'],
    },
)
