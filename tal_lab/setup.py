"""Build script of the ament_python package tal_lab (no nodes: experiments, datasets, training, reports)."""

from setuptools import find_packages, setup

PACKAGE = "tal_lab"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={PACKAGE: ["py.typed"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "README.md"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="tal developers",
    maintainer_email="tal-dev@example.com",
    description=open("README.md", encoding="utf-8").read().splitlines()[2],
    license="BSD-3-Clause",
)
