from setuptools import find_packages, setup

PACKAGE = "endo_io"

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
        "Message/numpy conversions, camera model, QoS presets and rosbag2-compatible "
        "MCAP replay and record for endo3d."
    ),
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "endo-replay = endo_io.replay_node:main",
            "endo-record = endo_io.record_node:main",
            "endo-bag = endo_io.bag_cli:main",
            "endo-camera = endo_io.camera_node:main",
        ],
    },
)
