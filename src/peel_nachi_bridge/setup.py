"""ament_python / pip build script for peel_nachi_bridge."""


from setuptools import find_packages, setup

package_name = "peel_nachi_bridge"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_nachi_bridge']),
        ('share/peel_nachi_bridge', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="Bridge to the Nachi robot controller over TCP (NACHI-PEEL 1).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'peel_nachi_bridge = peel_nachi_bridge.node:main'
        ],
        # the parameters this package's node declares (peel_msgs_py.params checks files by them)
        "peel.parameters": [
            'peel_nachi_bridge = peel_nachi_bridge.parameters:SPECS',
        ],
    },
)
