"""ament_python package: DC's launch file for colcon workspaces (DC itself is installed with pip)."""

from setuptools import setup

PACKAGE = "dc_launch"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=[],
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", ["launch/dc.launch.py"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="DC maintainers",
    maintainer_email="dc@example.com",
    description="Launch file starting DC (dc-bringup) with namespace, use_sim_time, params_file and log_level",
    license="MPL-2.0",
)
