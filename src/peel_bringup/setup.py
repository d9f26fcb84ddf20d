"""ament_python / pip build script for peel_bringup."""

from glob import glob

from setuptools import find_packages, setup

package_name = "peel_bringup"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_bringup']),
        ('share/peel_bringup', ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/config/foxglove', glob('config/foxglove/*.json')),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="The peel command, graph launcher, demo and launch file.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'peel = peel_bringup.cli:main'
        ],
        # the parameters this package's node declares (peel_msgs_py.params checks files by them)
        "peel.parameters": [
            'peel_bringup = peel_bringup.parameters:SPECS',
        ],
    },
)
