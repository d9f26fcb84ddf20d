"""ament_python / pip build script for peel_sim_node."""


from setuptools import find_packages, setup

package_name = "peel_sim_node"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/peel_sim_node']),
        ('share/peel_sim_node', ['package.xml']),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="peel developers",
    maintainer_email="dev@peel.invalid",
    description="PyBullet peeling simulator, reality-gap plant, datasets, simulator bridge node.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            'peel_sim_node = peel_sim_node.node:main'
        ],
        # the parameters this package's node declares (peel_msgs_py.params checks files by them)
        "peel.parameters": [
            'peel_sim_node = peel_sim_node.parameters:SPECS',
        ],
    },
)
