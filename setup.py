"""ament_python package that also installs with plain pip on a machine without ROS.

Two installers read this file, and they want the executables in different places:

* pip (any version: ``pyproject.toml`` makes even pip 23.0 build a PEP 517 / PEP 660 wheel, never
  ``setup.py develop``) puts ``nocal``, ``odometry_node`` and ``trainer_node`` on PATH (``bin``);
* colcon puts them where ``ros2 run`` looks, ``<prefix>/lib/nocal_ros``: ``setup.cfg`` says so for
  ``setup.py install`` (a wheel build overrides it), and :class:`ColconDevelop` for
  ``colcon build --symlink-install`` where setuptools has dropped what colcon calls.
"""

import sys
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.develop import develop as SetuptoolsDevelop

package_name = "nocal_ros"
console_scripts = [
    "nocal = nocal_ros.cli:main",
    "odometry_node = nocal_ros.ros.entry_points:odometry_node",
    "trainer_node = nocal_ros.ros.entry_points:trainer_node",
]


class ColconDevelop(SetuptoolsDevelop):
    """``setup.py develop`` as ``colcon build --symlink-install`` calls it, on setuptools >= 80.

    colcon (before 0.21, which falls back to a full install instead) runs ``setup.py develop --prefix P
    --editable --build-directory B --no-deps`` in its build directory, where it has symlinked
    ``setup.py`` and the package sources, and puts that directory on PYTHONPATH. Setuptools 80 turned
    ``develop`` into a shim for ``pip install -e`` that knows none of those options. This does what
    the old command did for colcon: the egg-info beside the symlinked sources, and one executable
    per console script in ``P/lib/nocal_ros``; ``--uninstall`` removes the executables again.
    Without ``--editable`` it is setuptools' own command.
    """

    user_options = SetuptoolsDevelop.user_options + [
        ("editable", "e", "develop in place, as colcon --symlink-install asks"),
        ("build-directory=", "b", "colcon's build directory (the sources are symlinked there)"),
        ("uninstall", "u", "remove what a previous develop installed"),
        ("install-layout=", None, "accepted for colcon on Debian; the executables go to lib/nocal_ros"),
    ]
    boolean_options = SetuptoolsDevelop.boolean_options + ["editable", "uninstall"]

    def initialize_options(self) -> None:
        super().initialize_options()
        self.editable = False
        self.build_directory = None
        self.uninstall = False
        self.install_layout = None

    def run(self) -> None:
        if not self.editable:
            super().run()
            return
        scripts = Path(self.prefix or sys.prefix) / "lib" / package_name
        entries = [(name.strip(), target.strip()) for name, target in (e.split("=", 1) for e in console_scripts)]
        if self.uninstall:
            for name, _ in entries:
                (scripts / name).unlink(missing_ok=True)
            return
        self.run_command("egg_info")
        scripts.mkdir(parents=True, exist_ok=True)
        for name, target in entries:
            module, function = target.split(":")
            path = scripts / name
            path.write_text(f"#!{sys.executable}\nimport sys\n\nfrom {module} import {function}\n\n"
                            f"if __name__ == '__main__':\n    sys.exit({function}())\n")
            path.chmod(0o755)


# Setuptools before 80 still has the develop colcon was written for (it reads setup.cfg's [install]).
develop_options = {option[0].rstrip("=") for option in SetuptoolsDevelop.user_options}
cmdclass = {} if "editable" in develop_options else {"develop": ColconDevelop}

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={package_name: ["models/*.safetensors", "models/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{package_name}"]),
        (f"share/{package_name}", ["package.xml"]),
        (f"share/{package_name}/launch", glob("launch/*.launch.py")),
        (f"share/{package_name}/config", glob("config/*.yaml") + glob("config/*.rviz")),
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
        "scipy",
        "threadpoolctl",
    ],
    extras_require={"eval": ["evo", "matplotlib"], "test": ["pytest", "kornia"], "compare": ["pycolmap==4.2.1", "gtsam==4.3.0", "evo", "matplotlib"]},
    zip_safe=False,
    maintainer="nocal_ros developers",
    maintainer_email="nocal@example.com",
    description="Visual odometry and camera calibration from an uncalibrated camera (NOCaL).",
    license="Apache-2.0",
    cmdclass=cmdclass,
    entry_points={"console_scripts": console_scripts},
)
