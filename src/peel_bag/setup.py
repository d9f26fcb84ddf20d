"""ament_python / pip build script for peel_bag."""

from setuptools import find_packages, setup

package_name = "peel_bag"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_bag']),
        ('share/peel_bag', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="MCAP recorder node and CLI, bag writer, reader and repair.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'peel_recorder = peel_bag.recorder_cli:node_main',
        ],
    },
)
