"""ament_python package that also installs with plain pip on a machine without ROS."""

from glob import glob

from setuptools import find_packages, setup

package_name = "nocal_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={package_name: ["models/*.safetensors", "models/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{package_name}"]),
        (f"share/{package_name}", ["package.xml"]),
        (f"share/{package_name}/launch", glob("launch/*.launch.py")),
        (f"share/{package_name}/config", glob("config/*.yaml")),
        (f"share/{package_name}/config/cameras", glob("config/cameras/*.yaml")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "torch>=2.3",
        "numpy",
        "opencv-python-headless",
        "rosbags>=0.10",
        "safetensors",
        "pyyaml",
        "tqdm",
        "scikit-image",
    ],
    extras_require={"eval": ["evo", "matplotlib"], "test": ["pytest", "kornia"], "compare": ["pycolmap==4.2.1", "evo", "matplotlib"]},
    zip_safe=True,
    maintainer="nocal_ros developers",
    maintainer_email="nocal@example.com",
    description="Visual odometry and camera calibration from an uncalibrated camera (NOCaL).",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "nocal = nocal_ros.cli:main",
            "odometry_node = nocal_ros.ros.odometry_node:main",
            "trainer_node = nocal_ros.ros.trainer_node:main",
        ],
    },
)
