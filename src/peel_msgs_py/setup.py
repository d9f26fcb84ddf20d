"""ament_python / pip build script for peel_msgs_py."""

from glob import glob

from setuptools import find_packages, setup

package_name = "peel_msgs_py"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_msgs_py']),
        ('share/peel_msgs_py', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="Interface contract of peel: topic names, QoS, message classes mirroring Jazzy, trajectory codec, SI/paper unit conversion, parameter loading, the embedded DDS runtime and the MCAP recorder.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            
        ],
    },
)
