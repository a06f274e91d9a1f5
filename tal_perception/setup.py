"""Build script of the ament_python package tal_perception."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "tal_perception"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={PACKAGE: ["py.typed", "models/*.pt"]},  # the weights the nodes load
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "README.md"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="tal developers",
    maintainer_email="tal-dev@example.com",
    description=open("README.md", encoding="utf-8").read().splitlines()[2],
    license="BSD-3-Clause",
    entry_points={
        "console_scripts": [
            "vfa = tal_perception.vfa_node:main",
            "vpa = tal_perception.vpa_node:main",
        ],
    },
)
