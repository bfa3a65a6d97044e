from setuptools import find_packages, setup

PACKAGE = "endo_calib"

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
        "Gray-card photometric calibration (camera response and light map) "
        "and the image correction node."
    ),
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "endo-calibrate = endo_calib.cli:main",
            "endo-photometric-correction = endo_calib.node:main",
            # The old name, kept for one release (0.1.x); it goes in 0.2.
            "photometric_correction = endo_calib.node:main",
        ],
    },
)
