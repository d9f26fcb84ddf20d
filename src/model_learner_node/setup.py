"""ament_python / pip build script for model_learner_node."""

from setuptools import find_packages, setup

package_name = "model_learner_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/model_learner_node']),
        ('share/model_learner_node', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="Offline training, MAML online learning, replay, held-out gate, learner node.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'model_learner_node = model_learner_node.node:main'
        ],
        # the parameters this package's node declares (peel_msgs_py.params checks files by them)
        "peel.parameters": [
            'model_learner_node = model_learner_node.parameters:SPECS',
        ],
    },
)
