from setuptools import find_packages, setup

PACKAGE = "endo_bringup"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        # `ros2 launch endo_bringup endo3d.launch.py` and its default parameter file
        ("share/" + PACKAGE + "/launch", ["launch/endo3d.launch.py"]),
        ("share/" + PACKAGE + "/config", ["config/endo3d.yaml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="endo3d developers",
    maintainer_email="dev@endo3d.org",
    description="Launch and demo entry points that wire the endo3d nodes into one graph.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "endo-doctor = endo_bringup.doctor:main",
            "endo-demo = endo_bringup.demo:main",
            "endo-launch = endo_bringup.launcher:main",
        ],
    },
)
