"""ament_python / pip build script for peel_experiments."""

from setuptools import find_packages, setup

package_name = "peel_experiments"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_experiments']),
        ('share/peel_experiments', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="Experiments, grids, reports, soak and benchmarks.",
    license="Apache-2.0",
)
