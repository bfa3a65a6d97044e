from setuptools import find_packages, setup

PACKAGE = "endo_flow"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="endo3d developers",
    maintainer_email="dev@endo3d.org",
    description=(
        "Lucas-Kanade flow and tracker poses to absolute scale, metric depth"
        " and world-frame point clouds."
    ),
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "endo-flow = endo_flow.node:main",
        ],
    },
)
