"""ament_python / pip build script for peel_model."""

from setuptools import find_packages, setup

package_name = "peel_model"

setup(
    name=package_name,
    version="0.1.0",
    # the shipped checkpoint: a data folder, listed as a package so that setuptools ships it
    packages=[*find_packages(exclude=["test"]), f"{package_name}.checkpoints"],
    package_data={f"{package_name}.checkpoints": ["*.safetensors", "*.json", "*.md"]},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_model']),
        ('share/peel_model', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="Forward model f_theta and baselines, predictor, compensated model, checkpoints, model versions.",
    license="Apache-2.0",
)
