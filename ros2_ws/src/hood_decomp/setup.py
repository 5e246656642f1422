from glob import glob

from setuptools import find_packages, setup

package_name = "hood_decomp"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "tests"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.xml")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs test/ with pytest
    zip_safe=False,
    maintainer="hood_decomp developers",
    maintainer_email="hood-decomp@example.com",
    description="Decompose scanned deviations of sheet-metal assemblies into boundary effects.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "hood-decomp = hood_decomp.cli:entry",
            "scan_node = hood_decomp.ros.scan_node:main",
            "estimator_node = hood_decomp.ros.estimator_node:main",
            "decomposition_node = hood_decomp.ros.decomposition_node:main",
        ],
    },
)
