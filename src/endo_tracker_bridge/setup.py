from setuptools import find_packages, setup

PACKAGE = "endo_tracker_bridge"

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
        "Optical tracker (ROS, OpenIGTLink, NDI, CSV) to camera pose "
        "through hand-eye and clock calibration."
    ),
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "endo-tracker-bridge = endo_tracker_bridge.node:main",
            "endo-handeye = endo_tracker_bridge.handeye_cli:main",
        ],
    },
)
