"""Rewrite build-machine paths in the ROS wheels' CMake export files to this interpreter's paths.

The Kilted wheels carry `/opt/python/cp311-cp311/include/python3.11` and that interpreter's numpy include directory in
their `*__rosidl_generator_pyExport.cmake` files; CMake then refuses to generate ("includes non-existent path").
Idempotent: prints how many files it changed.
"""

import pathlib
import sys
import sysconfig

import numpy

BUILD_PYTHON_INCLUDE = "/opt/python/cp311-cp311/include/python3.11"
BUILD_NUMPY_INCLUDE = "/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include"


def main() -> int:
    prefix = pathlib.Path(sys.prefix)
    replacements = {
        BUILD_PYTHON_INCLUDE: sysconfig.get_paths()["include"],
        BUILD_NUMPY_INCLUDE: numpy.get_include(),
    }
    changed = 0
    for path in prefix.glob("share/**/*.cmake"):
        text = path.read_text()
        new = text
        for old, replacement in replacements.items():
            new = new.replace(old, replacement)
        if new != text:
            path.write_text(new)
            changed += 1
    print(f"fix_wheel_cmake: {changed} CMake export file(s) rewritten")
    return 0


if __name__ == "__main__":
    sys.exit(main())
