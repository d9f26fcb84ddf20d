"""ament_python / pip build script for peel_nachi_emulator."""

from setuptools import find_packages, setup

package_name = "peel_nachi_emulator"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_nachi_emulator']),
        ('share/peel_nachi_emulator', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="Nachi controller emulator (NACHI-PEEL 1 over TCP) over the peeling plant, with faults.",
    license="Apache-2.0",
)
