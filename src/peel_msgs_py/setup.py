"""ament_python / pip build script for peel_msgs_py."""


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
    description="peel interfaces: topics, QoS, codec, units, params, diagnostics, rclpy helpers.",
    license="Apache-2.0",
)
