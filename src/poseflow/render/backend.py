"""Open3D, the renderer's backend, imported with an error that says what to install.

Open3D's wheels load system libraries (OpenGL, EGL, libusb, OpenMP) that a minimal machine or
container lacks; the import then fails with an ``OSError`` or ``ImportError`` naming a ``.so``
file. :func:`import_open3d` turns that into a
:class:`~poseflow.errors.MissingSystemLibraryError` naming the library and the apt package that
provides it, and a missing Open3D into a :class:`~poseflow.errors.MissingDependencyError`.
"""

from __future__ import annotations

import importlib
import re
from types import ModuleType

from poseflow.errors import MissingDependencyError, MissingSystemLibraryError

__all__ = ["APT_PACKAGES", "OPEN3D_SYSTEM_PACKAGES", "import_open3d", "system_library_error"]

#: Debian/Ubuntu package of each shared library Open3D's wheels load.
APT_PACKAGES: dict[str, str] = {
    "libGL.so": "libgl1",
    "libEGL.so": "libegl1",
    "libOpenGL.so": "libopengl0",
    "libGLX.so": "libglx0",
    "libGLdispatch.so": "libglvnd0",
    "libusb-1.0.so": "libusb-1.0-0",
    "libgomp.so": "libgomp1",
    "libX11.so": "libx11-6",
    "libXext.so": "libxext6",
    "libXrender.so": "libxrender1",
    "libXi.so": "libxi6",
    "libXfixes.so": "libxfixes3",
    "libXxf86vm.so": "libxxf86vm1",
    "libudev.so": "libudev1",
    "libstdc++.so": "libstdc++6",
}

#: Every package Open3D needs on a minimal Debian/Ubuntu system (what ``make sysdeps`` installs).
OPEN3D_SYSTEM_PACKAGES = "libgl1 libegl1 libusb-1.0-0 libgomp1"

_LIBRARY = re.compile(r"(lib[\w.+-]*?\.so)(\.[\d.]+)?")


def system_library_error(
    exc: BaseException, *, package: str = "open3d", purpose: str = ""
) -> MissingSystemLibraryError | None:
    """The :class:`MissingSystemLibraryError` that an import error stands for, or None.

    Args:
        exc: the ``ImportError`` or ``OSError`` raised by the import.
        package: the package that was imported.
        purpose: what it is needed for, for the message.

    Returns:
        The error naming the library and its apt package, or None when ``exc`` does not name a
        shared library that could not be opened.

    Example:
        >>> e = OSError("libGL.so.1: cannot open shared object file: No such file or directory")
        >>> print(str(system_library_error(e)).split("; ")[1])
        install it with `sudo apt-get install libgl1` (or your system's equivalent)
    """
    text = str(exc)
    if "cannot open shared object" not in text and "shared object" not in text:
        return None
    m = _LIBRARY.search(text)
    if m is None:
        return MissingSystemLibraryError(package, "", OPEN3D_SYSTEM_PACKAGES, purpose)
    library = m.group(1) + (m.group(2) or "")
    apt = APT_PACKAGES.get(m.group(1), OPEN3D_SYSTEM_PACKAGES)
    return MissingSystemLibraryError(package, library, apt, purpose)


def import_open3d(purpose: str = "rendering and mesh I/O") -> ModuleType:
    """Import and return ``open3d``, or raise an error that says what to install.

    Args:
        purpose: what Open3D is needed for, for the message.

    Returns:
        The ``open3d`` module.

    Raises:
        MissingSystemLibraryError: a system library Open3D loads is missing (names the apt
            package).
        MissingDependencyError: Open3D itself is not installed.
    """
    try:
        return importlib.import_module("open3d")
    except (ImportError, OSError) as exc:
        err = system_library_error(exc, purpose=purpose)
        if err is not None:
            raise err from exc
        if isinstance(exc, ModuleNotFoundError) and exc.name == "open3d":
            raise MissingDependencyError(
                "open3d", None, purpose, install="pip install open3d"
            ) from exc
        raise
