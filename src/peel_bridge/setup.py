"""ament_python / pip build script for peel_bridge."""


from setuptools import find_packages, setup

package_name = "peel_bridge"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_bridge']),
        ('share/peel_bridge', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="The core of both plant bridges: task loop, publishers, model following.",
    license="Apache-2.0",
)
