from setuptools import find_packages, setup

PACKAGE = "endo_foxglove"

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
        "Live Foxglove view of the endo3d graph without foxglove_bridge: images, depth, "
        "camera calibration, world clouds and map, camera transforms and the scale over "
        "foxglove-sdk's WebSocket server."
    ),
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "endo-foxglove = endo_foxglove.node:main",
        ],
    },
)
