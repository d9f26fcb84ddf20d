"""ament_python / pip build script for peel_planner_node."""

from setuptools import find_packages, setup

package_name = "peel_planner_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["csrc/*.cpp"]},  # the C++ rollout loop, built on first use
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_planner_node']),
        ('share/peel_planner_node', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="OL-MPPI planner library and the planner node.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'peel_planner_node = peel_planner_node.node:main'
        ],
        # the parameters this package's node declares (peel_msgs_py.params checks files by them)
        "peel.parameters": [
            'peel_planner_node = peel_planner_node.parameters:SPECS',
        ],
    },
)
