"""ament_python / pip build script for peel_residual."""

from setuptools import find_packages, setup

package_name = "peel_residual"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_residual']),
        ('share/peel_residual', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="peel residual: the model's residual on bags traced to physical effects, added, reported.",
    license="Apache-2.0",
    entry_points={
        # the parameters this package declares (peel_msgs_py.params checks files by them)
        "peel.parameters": [
            'peel_residual = peel_residual.params:RESIDUAL_SPECS',
        ],
    },
)
